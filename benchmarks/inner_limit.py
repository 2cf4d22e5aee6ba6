"""What each nulled nuisance costs the contrast limits, separation by separation.

    python benchmarks/inner_limit.py [--sim] [--seed 0] [--sci F... --cal F...] [--out DIR]

The DISCOs are made blind to the instrument's nuisances (docs/fit.md, "DISCOs"): 70
Zernikes, log-flux, spectral slope, defocus, the jitter, and the 16 envelope-knot
visibilities. Each direction nulled is information a companion loses where its signal
looks like that nuisance, which happens most at small separations. This script fits one
science/calibrator set once (``amigo fit``, in this process), keeps each filter's latent
estimates, covariances and nuisance columns, and rebuilds the DISCOs with other sets of
nuisances nulled, to print per filter and per set:

* ``n``: the number of DISCOs; ``chi2/n``: of the calibrated DISCOs against zero (a
  companion in the data raises it);
* the linearised 3-sigma limits at 100 / 150 / 200 / 400 mas, each the mean over 72
  position angles of a companion's signal in the DISCOs, written ``Absil/1-dof``: the
  Absil test amigo reports (the chi2 of ``n`` observables; ``amigo.companions.limits.
  absil_limit`` at zero fitted contrast and chi2 = n) and three sigma of the contrast at
  a known position (what ``n`` does not penalise);
* rows ``jitter marginalised``: the jitter not nulled but its uncertainty carried into
  the latent covariance, ``g g^T (s_sci^2 + s_cal^2)`` with ``g`` the jitter's column and
  ``s`` the science and calibrator exposures' fitted jitter errors (fit_summary.json),
  and with those errors doubled and halved.

The companion's signal is linear in its contrast (the log-visibility's first order in a
flux ratio of 1e-4, ``amigo.companions.models.scene_visibility``), evaluated at the
basis's knots in the pupil frame: rings are the same on the sky up to the detector's
anisotropy (1e-3). ``--sim`` fits ``benchmarks/peers.py``'s companion-free simulated
F480M pair (seed ``--seed``; one minute to simulate); the default is the real COM 1093
files (AB Dor, obs 12, against HD 37093, obs 15, three filters) from ../shared, whose
limits carry AB Dor C (its signal is not subtracted: the rows compare nuisance sets, not
targets). Nothing is asserted; about a minute for the fit on a 2-core CPU once its
programs are cached.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

SEPARATIONS_MAS = (100.0, 150.0, 200.0, 400.0)
N_ANGLES = 72
PROBE_CONTRAST = 1e-4


@dataclass
class Captured:
    """What one filter's extraction leaves for the study."""

    filter_name: str
    nuisance: np.ndarray  # (m, n) G, named by `names`
    names: list[str]
    n_amp: int
    to_knots: np.ndarray  # (m, 2 k) knot log-visibilities -> latents
    knots_m: np.ndarray  # (k, 2) the basis's knots, pupil frame
    wavelengths_m: np.ndarray
    weights: np.ndarray
    value: np.ndarray  # (m,) calibrated latents of the (first) science target
    covariance: np.ndarray  # (m, m) their covariance


def capture_fit(sci: list[Path], cal: list[Path], out: Path, model: Path | None) -> list[Captured]:
    """Run ``amigo fit`` in this process and keep each filter's extraction."""
    from amigo import niriss as nis
    from amigo.cli import main as amigo_main
    from amigo.observables import extract

    captured: list[Captured] = []
    original = extract.extract_filter

    def keep(instrument, filter_name, *args, **kwargs):
        product = original(instrument, filter_name, *args, **kwargs)
        basis = product.fit.setup.basis
        assert basis is not None  # a fitted filter's setup has its latent basis
        nuisance, names = extract.kernel_nuisances(product.fit, product.information)
        target = product.products[0]
        bins = nis.filter_bins(filter_name, instrument.n_wavelengths)
        captured.append(
            Captured(
                filter_name=filter_name,
                nuisance=nuisance,
                names=names,
                n_amp=basis.n_amp,
                to_knots=basis.latent_from_knots(),
                knots_m=basis.knots_m(),
                wavelengths_m=np.asarray(bins.wavelengths_m, float),
                weights=np.asarray(bins.weights, float),
                value=target.calibrated_latent,
                covariance=target.calibrated_covariance,
            )
        )
        return product

    args = ["fit", "--sci", *map(str, sci), "--cal", *map(str, cal), "--out", str(out)]
    args += ["--force"] + (["--model", str(model)] if model else [])
    extract.extract_filter = keep
    try:
        amigo_main(args)
    except SystemExit as stop:  # the command's exit status: 0 when every filter is fitted
        if stop.code:
            raise
    finally:
        extract.extract_filter = original
    return captured


def jitter_errors(summary: Path) -> dict[str, float]:
    """Per filter, ``sqrt(sum of the squared fitted jitter errors)`` over its exposures."""
    exposures = json.loads(summary.read_text())["exposures"]
    out: dict[str, float] = {}
    for e in exposures:
        err = e.get("jitter_mas_err")
        if err is not None:
            out[e["filter"]] = float(np.hypot(out.get(e["filter"], 0.0), err))
    return out


def companion_signal(c: Captured, sep_mas: float) -> np.ndarray:
    """(N_ANGLES, 2 k) ``d [log|V|, arg V] / d contrast`` at the knots for a companion
    at ``sep_mas`` around a ring."""
    import jax.numpy as jnp

    from amigo.companions.models import scene_visibility

    angles = np.linspace(0.0, 2 * np.pi, N_ANGLES, endpoint=False)
    rows = []
    for a in angles:
        offset = jnp.asarray([[sep_mas * np.sin(a), sep_mas * np.cos(a)]])
        vis = scene_visibility(
            c.knots_m, c.wavelengths_m, c.weights, offset, jnp.asarray([PROBE_CONTRAST])
        )
        log_vis = np.log(np.asarray(vis, np.complex128))
        rows.append(np.concatenate([log_vis.real, log_vis.imag]) / PROBE_CONTRAST)
    return np.asarray(rows)


def limits(c: Captured, columns: list[int], extra_cov: np.ndarray | None, signals) -> str:
    """One table row: DISCOs nulling ``columns`` of ``c.nuisance``; ``extra_cov`` added
    to the calibrated covariance."""
    from amigo.companions.limits import absil_limit, to_dmag
    from amigo.observables import kernel as obs

    kernel = obs.build_kernel(c.nuisance[:, columns], c.n_amp)
    cov = c.covariance if extra_cov is None else c.covariance + extra_cov
    zero = np.zeros_like(c.value)
    discos = obs.discos(c.value, cov, zero, np.zeros_like(cov), kernel, c.to_knots)
    n = len(discos.errors)
    chi2 = float(np.sum((discos.values / discos.errors) ** 2))
    cells = []
    for signal in signals:
        fisher = np.sum(((signal @ discos.matrix.T) / discos.errors) ** 2, axis=1)
        sigma = 1.0 / np.sqrt(fisher)
        absil = np.mean(to_dmag(absil_limit(np.zeros_like(sigma), sigma, float(n), n)))
        single = np.mean(to_dmag(3.0 * sigma))
        cells.append(f"{absil:5.2f}/{single:4.2f}")
    return f"{n:5d} {chi2 / n:7.3f}  " + "  ".join(cells)


def study(c: Captured, jitter_err: float | None) -> None:
    names = c.names
    every = list(range(len(names)))
    zernike = [i for i, n in enumerate(names) if n.startswith("z")]
    envelope = [i for i, n in enumerate(names) if n.startswith("env_")]
    scalars = [names.index(n) for n in ("log_flux", "slope", "defocus", "jitter_mas")]
    jitter = names.index("jitter_mas")

    def without(*drop):
        gone = {i for d in drop for i in (d if isinstance(d, list) else [d])}
        return [i for i in every if i not in gone]

    def noll(orders):
        return [i for i in zernike if int(names[i].split("_")[1]) in orders]

    sets = [
        ("every nuisance (amigo's DISCOs)", every),
        ("without the jitter", without(jitter)),
        ("without the envelope knots", without(envelope)),
        ("the paper's (no jitter, no envelope)", without(jitter, envelope)),
        ("Zernikes Noll 1-3 only", noll({1, 2, 3}) + scalars + envelope),
        ("Zernikes Noll 1-6 only", noll(set(range(1, 7))) + scalars + envelope),
        ("without the Zernikes", without(zernike)),
        ("without the log-flux", without(names.index("log_flux"))),
        ("without the slope", without(names.index("slope"))),
        ("without the defocus", without(names.index("defocus"))),
    ]
    signals = [companion_signal(c, s) for s in SEPARATIONS_MAS]
    seps = "  ".join(f"{s:>10.0f}" for s in SEPARATIONS_MAS)
    print(f"\n{c.filter_name}: 3-sigma limits (delta-mag, Absil/1-dof) at mas {seps}")
    print(f"{'nulled':<40} {'n':>5} {'chi2/n':>7}")
    for label, columns in sets:
        print(f"{label:<40} {limits(c, columns, None, signals)}")
    if jitter_err is not None:
        g = c.nuisance[:, jitter]
        for factor in (0.5, 1.0, 2.0):
            s = factor * jitter_err
            row = limits(c, without(jitter), np.outer(g, g) * s**2, signals)
            print(f"{f'jitter marginalised, {s:.2f} mas':<40} {row}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim", action="store_true", help="peers.py's simulated F480M pair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sci", type=Path, nargs="+")
    parser.add_argument("--cal", type=Path, nargs="+")
    parser.add_argument("--model", type=Path)
    parser.add_argument("--out", type=Path, default=Path("inner_limit"))
    args = parser.parse_args()

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    model = args.model
    if args.sci or args.cal:
        if not (args.sci and args.cal):
            parser.error("--sci and --cal go together")
        sci, cal = list(args.sci), list(args.cal)
    elif args.sim:
        sci, cal, model = simulated_pair(out / "sim", args.seed)
    else:
        from peers import CALIBRATOR, EXPOSURE, SCIENCE, SHARED

        if not SHARED.is_dir():
            sys.exit(f"inner_limit: no real files at {SHARED}; give --sci/--cal or --sim")
        sci = [SHARED / SCIENCE.format(e) for e in EXPOSURE.values()]
        cal = [SHARED / CALIBRATOR.format(e) for e in EXPOSURE.values()]
    captured = capture_fit(sci, cal, out / "fit", model)
    errors = jitter_errors(out / "fit" / "fit_summary.json")
    for c in captured:
        study(c, errors.get(c.filter_name))


def simulated_pair(out: Path, seed: int) -> tuple[list[Path], list[Path], Path]:
    """peers.py's companion-free F480M science file and its calibrator, and the nominal
    instrument they are fitted with."""
    from peers import CALIBRATOR_XY, SCIENCE_XY, _render, simulation_setup, write_calints

    model, template, orientation = simulation_setup(out, "F480M")
    nothing = (None, None, None)
    cal_image = _render("F480M", orientation, CALIBRATOR_XY, nothing, seed)
    cal = write_calints(out / "jw09999002001_03102_00001_nis_calints.fits", template,
                        cal_image, "CAL-STAR", "002", seed + 1000)  # fmt: skip
    image = _render("F480M", orientation, SCIENCE_XY, nothing, seed)
    sci = write_calints(out / "jw09999001001_03102_00001_nis_calints.fits", template, image,
                        "SCI-STAR", "001", seed)  # fmt: skip
    return [sci], [cal], model


if __name__ == "__main__":
    main()
