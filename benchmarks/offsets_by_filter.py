"""Where each filter puts a companion: its offset from the truth, linearised, by filter.

    python benchmarks/offsets_by_filter.py RUN_DIR [RUN_DIR ...] [--companion 1]

For a simulated run (``amigo run`` output with the simulator's ``raw/*_truth.json``; for
example each ``noise_M`` folder of ``benchmarks/go1843.py --noise-seeds``), the calibrated
observables' residuals under the true scene are projected on one companion's radial and
tangential offsets (its flux ratio in each filter free, the other companions held at
their truth): a Gauss-Newton step from the truth, per filter, per kind of observable and
for all together, with the error scales ``amigo detect`` fitted (``companions.json``).
Each line gives the step in mas and in units of its error (z). Independent noise in the
filters gives independent z's; a fit's offset that every filter shares is the scene's or
the model's, not the noise's. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from amigo.companions.fit import block_residual
from amigo.companions.models import dmag_to_contrast
from amigo.companions.observables import Dataset, load, select_kinds

jax.config.update("jax_enable_x64", True)


def _truth(run: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The true companions' offsets (K, 2) mas and, per filter, their flux ratios (K,)."""
    offsets = None
    ratios: dict[str, np.ndarray] = {}
    for path in sorted((run / "raw").glob("*_truth.json")):
        doc = json.loads(path.read_text())
        if doc["exposure"]["role"] != "science":
            continue
        scene = doc["scene"]["companions"]
        offsets = np.array([[c["dra_mas"], c["ddec_mas"]] for c in scene])
        ratios[doc["exposure"]["filter"]] = dmag_to_contrast(np.array([c["dmag"] for c in scene]))
    if offsets is None:
        raise SystemExit(f"{run}: no science truth file under raw/")
    return offsets, ratios


def _step(blocks, scales, offsets, ratios, k):
    """Gauss-Newton step from the truth for companion ``k``: (radial, tangential) mas and
    their errors. Parameters: the two offsets and ``log10`` of ``k``'s flux ratio in each
    filter of ``blocks``."""
    filters = sorted({b.filter_name for b in blocks})
    radial = offsets[k] / np.hypot(*offsets[k])
    tangential = np.array([radial[1], -radial[0]])

    def residuals(p):
        out = []
        for block, scale in zip(blocks, scales, strict=True):
            position = offsets[k] + p[0] * radial + p[1] * tangential
            moved = jnp.asarray(offsets).at[k].set(position)
            f = filters.index(block.filter_name)
            flux = jnp.asarray(ratios[block.filter_name]).at[k].multiply(10.0 ** p[2 + f])
            out.append(block_residual(block, moved, flux) / scale)
        return jnp.concatenate(out)

    p0 = jnp.zeros(2 + len(filters))
    r = np.asarray(residuals(p0))
    jac = np.asarray(jax.jacfwd(residuals)(p0))
    cov = np.linalg.inv(jac.T @ jac)
    step = -cov @ jac.T @ r
    return step[:2], np.sqrt(np.diag(cov)[:2])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument(
        "--companion", type=int, default=1, help="which true companion (0: the first listed)"
    )
    args = parser.parse_args()
    print("| run | subset | radial mas (z) | tangential mas (z) |")
    print("|---|---|---|---|")
    for run in args.runs:
        offsets, ratios = _truth(run)
        doc = json.loads((run / "companions.json").read_text())
        by_kind = doc["sigma_scale_by_kind"]
        blocks = [load(p) for p in sorted(run.glob("*_calvis.fits"))]
        blocks = [b for b in blocks if b.filter_name in ratios]
        subsets: list[tuple[str, list]] = []
        for f in sorted({b.filter_name for b in blocks}):
            subsets.append((f, [b for b in blocks if b.filter_name == f]))
        for kind in ("amplitude", "phase"):
            picked = [select_kinds(b, [kind]) for b in blocks]
            subsets.append((f"all {kind}s", [b for b in picked if b is not None]))
        subsets.append(("all", blocks))
        for name, chosen in subsets:
            # One scale per (filter, kind) group, as amigo detect fits them.
            dataset = Dataset.from_blocks(chosen)
            scales = [
                np.array([by_kind[block.filter_name][k] for k in _kind_names(block)])
                for block in dataset.blocks
            ]
            step, err = _step(dataset.blocks, scales, offsets, ratios, args.companion)
            cells = [f"{s:+.1f} ({s / e:+.2f})" for s, e in zip(step, err, strict=True)]
            print(f"| {run.name} | {name} | {cells[0]} | {cells[1]} |")


def _kind_names(block) -> list[str]:
    names = ("amplitude", "phase")
    return [names[k] for k in block.kinds]


if __name__ == "__main__":
    main()
