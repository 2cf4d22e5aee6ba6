"""Latent visibility bases: build, truncate, cache (the paper's "Latent Visibility Model").

For one filter and one instrument state:

1. ``J``: the Jacobian of the 80 x 80 image of a centred unit-flux point source with
   respect to the free log-amplitudes and phases of the knot grid, at ``V = 1`` (computed
   column by column with ``jax.linearize`` of the forward model itself, only for the
   knots whose interpolation footprint touches the OTF: the others have zero columns).
2. The Gauss-Newton Hessians with identity pixel covariance, ``H_a = J_a^T J_a`` and
   ``H_p = J_p^T J_p`` (amplitudes and phases are kept separate, as in the paper; their
   cross term vanishes for a centro-symmetric PSF).
3. ``H = Q Lambda Q^T`` by ``numpy.linalg.eigh``, sorted by decreasing eigenvalue.
4. Truncation where the modes leave the OTF support: a knot is *inside* the support when
   the band-averaged MTF there (``|OTF|`` normalised to 1 at zero baseline) exceeds
   :data:`SUPPORT_MTF` (1e-3, i.e. 0.7 % of a splodge peak of 1/7); the basis keeps the
   leading modes up to the first one that has less than :data:`MIN_SUPPORT_FRACTION`
   of its energy on inside knots.

Bases depend on the instrument (base model), the filter and the knot grid. They are
cached in ``$AMIGO_CACHE_DIR`` (default ``$XDG_CACHE_HOME/amigo`` or ``~/.cache/amigo``)
under a name holding the format version and a hash of every input; bases shipped in
``amigo/data/bases`` (none yet: a basis is ~1.5 MB per filter, 5 MB for three) are
found the same way. A build takes about a minute per filter on two CPU cores and shows
a progress bar.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from amigo._version import __version__
from amigo.cachedir import cache_dir
from amigo.model.image import FilterSetup, Instrument, OpticsParams, filter_psfs, unit_image
from amigo.model.visibility import LatentBasis, UVGrid
from amigo.progress import step, track

#: Version of the basis algorithm and file layout (part of the cache key).
BASIS_FORMAT = 2
#: MTF level that bounds the OTF support (see module notes).
SUPPORT_MTF = 1e-3
#: A mode is kept while at least this fraction of its energy lies inside the support.
MIN_SUPPORT_FRACTION = 0.5
#: A knot is computed when its footprint sees at least this fraction of the peak OTF.
TOUCH_FRACTION = 1e-8
#: Jacobian columns per batch (memory ~ batch x n_lambda x fft^2 complex).
BATCH = 16


@dataclass(frozen=True)
class BasisInfo:
    """Diagnostics of a basis build (all NumPy).

    Attributes
    ----------
    filter_name
        Filter.
    key
        Cache key (hash of the inputs).
    amp_eigenvalues, phase_eigenvalues
        (n_used,) all eigenvalues, descending (unit-flux image, identity pixel weights).
    amp_support_fraction, phase_support_fraction
        (n_used,) fraction of each mode's energy on knots inside the OTF support.
    n_amp, n_phase
        Modes kept.
    n_knots_used, n_knots_support
        Knots whose columns were computed, and knots inside the support.
    seconds
        Build time.
    """

    filter_name: str
    key: str
    amp_eigenvalues: np.ndarray
    phase_eigenvalues: np.ndarray
    amp_support_fraction: np.ndarray
    phase_support_fraction: np.ndarray
    n_amp: int
    n_phase: int
    n_knots_used: int
    n_knots_support: int
    seconds: float


def basis_key(instrument: Instrument, filter_name: str, grid: UVGrid) -> str:
    """Hash of everything a basis depends on: format, filter, grid, instrument arrays."""
    h = hashlib.sha256()
    h.update(
        f"basis-format-{BASIS_FORMAT}|{filter_name}|{grid.n_knots}|{grid.spacing_m!r}".encode()
    )
    h.update(f"|{instrument.n_wavelengths}|{SUPPORT_MTF}|{MIN_SUPPORT_FRACTION}".encode())
    h.update(repr(instrument.optics.config).encode())
    for leaf in jax.tree.leaves(instrument):
        if isinstance(leaf, jax.Array | np.ndarray):
            h.update(np.asarray(leaf, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _file_name(filter_name: str, key: str) -> str:
    return f"basis_v{BASIS_FORMAT}_{filter_name}_{key}.npz"


# ------------------------------------------------------------------------------ build
def knot_mtf(
    psfs: np.ndarray,
    weights: np.ndarray,
    wavelengths_m: np.ndarray | jax.Array,
    pixel_rad: float,
    uv_m: np.ndarray,
) -> np.ndarray:
    """Band-averaged MTF ``sum_l w_l |OTF_l(b / l)| / OTF_l(0)`` at baselines ``uv_m``.

    A direct Fourier sum over the (n, n) PSF samples (independent of the injection's
    interpolation). ``psfs`` (n_lambda, n, n), ``uv_m`` (k, 2).
    """
    n = psfs.shape[-1]
    theta = (np.arange(n) - (n - 1) / 2) * pixel_rad
    out = np.zeros(len(uv_m))
    for psf, w, wl in zip(psfs, weights, wavelengths_m, strict=True):
        ex = np.exp(-2j * np.pi * np.outer(uv_m[:, 0] / wl, theta))
        ey = np.exp(-2j * np.pi * np.outer(uv_m[:, 1] / wl, theta))
        out += w * np.abs(np.einsum("ky,yx,kx->k", ey, psf, ex)) / psf.sum()
    return out


def _touched_knots(setup: FilterSetup, psfs: jax.Array) -> np.ndarray:
    """Free-knot indices whose interpolation footprint meets a non-zero OTF."""
    inj = setup.injector
    otf = np.abs(np.asarray(inj.otf(psfs)))[:, np.asarray(inj.rows), : inj.nx_band]
    reach = np.einsum(
        "lyi,lyx,lxj->ij", np.abs(np.asarray(inj.w_y)), otf, np.abs(np.asarray(inj.w_x))
    )
    # The rfft holds only u >= 0; |OTF| is point-symmetric, so mirror the reach.
    reach = (reach + reach[::-1, ::-1]).ravel()
    half = setup.grid.half_indices()
    return np.nonzero(reach[half] > TOUCH_FRACTION * reach.max())[0]


@eqx.filter_jit
def _columns(instrument: Instrument, setup: FilterSetup, index: jax.Array, which: int):
    """Jacobian columns of :func:`unit_image` for the free knots ``index`` (batch, ...)."""
    n_half = setup.grid.n_half
    zero = jnp.zeros(n_half, setup.injector.w_y.dtype)

    def one(k):
        unit = jax.nn.one_hot(k, n_half, dtype=zero.dtype)
        tangents = (unit, zero) if which == 0 else (zero, unit)
        return jax.jvp(lambda a, p: unit_image(instrument, setup, a, p), (zero, zero), tangents)[1]

    return jax.vmap(one)(index).reshape(index.shape[0], -1)


def _jacobian(
    instrument: Instrument, setup: FilterSetup, knots: np.ndarray, which: int, label: str
) -> np.ndarray:
    """(6400, len(knots)) columns of the image Jacobian for amplitudes (0) or phases (1)."""
    batches = [knots[i : i + BATCH] for i in range(0, len(knots), BATCH)]
    out = []
    for batch in track(batches, label):
        padded = np.pad(batch, (0, BATCH - len(batch)), mode="edge")  # one compiled shape
        cols = _columns(instrument, setup, jnp.asarray(padded), which)
        out.append(np.asarray(cols, dtype=np.float64)[: len(batch)])
    return np.concatenate(out).T


def _truncate(
    hessian: np.ndarray, inside: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Sorted eigen-decomposition and the number of modes kept (see module notes)."""
    evals, evecs = np.linalg.eigh(0.5 * (hessian + hessian.T))
    order = np.argsort(evals)[::-1]
    evals, evecs = evals[order], evecs[:, order]
    fraction = np.sum(evecs[inside] ** 2, axis=0)
    outside = np.nonzero(fraction < MIN_SUPPORT_FRACTION)[0]
    n_keep = int(outside[0]) if outside.size else len(evals)
    # Fix each eigenvector's sign (eigh's is arbitrary) so that bases are reproducible.
    signs = np.sign(evecs[np.argmax(np.abs(evecs), axis=0), np.arange(evecs.shape[1])])
    return evals, evecs * signs, fraction, n_keep


def build_basis(
    instrument: Instrument, filter_name: str, grid: UVGrid | None = None
) -> tuple[LatentBasis, BasisInfo]:
    """Build the latent basis of ``filter_name`` for ``instrument`` (see module notes)."""
    import time

    start = time.perf_counter()
    grid = UVGrid() if grid is None else grid
    setup = FilterSetup.create(filter_name, instrument, grid=grid)
    spectrum = setup.spectrum(jnp.zeros((), jnp.float32))
    psfs = filter_psfs(instrument, setup, OpticsParams.from_instrument(instrument))
    knots = _touched_knots(setup, psfs)
    step(f"basis {filter_name}: {len(knots)} of {grid.n_half} knots reach the OTF")
    j_amp = _jacobian(instrument, setup, knots, 0, f"basis {filter_name}: amplitude Jacobian")
    j_pha = _jacobian(instrument, setup, knots, 1, f"basis {filter_name}: phase Jacobian")
    mtf = knot_mtf(
        np.asarray(psfs, dtype=float),
        np.asarray(spectrum.weights(), dtype=float),
        setup.wavelengths_m,
        instrument.psf_pixel_rad,
        grid.half_knots_m()[knots],
    )
    inside = mtf > SUPPORT_MTF
    ea, va, fa, na = _truncate(j_amp.T @ j_amp, inside)
    ep, vp, fp, npha = _truncate(j_pha.T @ j_pha, inside)
    basis = LatentBasis(
        amp=jnp.asarray(va[:, :na], jnp.float32),
        phase=jnp.asarray(vp[:, :npha], jnp.float32),
        knots=tuple(int(k) for k in knots),
        grid=grid,
    )
    info = BasisInfo(
        filter_name=filter_name,
        key=basis_key(instrument, filter_name, grid),
        amp_eigenvalues=ea,
        phase_eigenvalues=ep,
        amp_support_fraction=fa,
        phase_support_fraction=fp,
        n_amp=na,
        n_phase=npha,
        n_knots_used=len(knots),
        n_knots_support=int(inside.sum()),
        seconds=time.perf_counter() - start,
    )
    step(f"basis {filter_name}: kept {na} amplitude and {npha} phase modes ({info.seconds:.0f} s)")
    return basis, info


# ------------------------------------------------------------------------------ files
def save_basis(path: Path, basis: LatentBasis, info: BasisInfo) -> None:
    """Write a basis and its diagnostics to an ``.npz`` file (atomically)."""
    from amigo.io.atomic import atomic_path

    meta = {
        "format": BASIS_FORMAT,
        "amigo_version": __version__,
        "filter": info.filter_name,
        "key": info.key,
        "n_knots": basis.grid.n_knots,
        "spacing_m": basis.grid.spacing_m,
        "n_amp": info.n_amp,
        "n_phase": info.n_phase,
        "n_knots_used": info.n_knots_used,
        "n_knots_support": info.n_knots_support,
        "seconds": info.seconds,
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(
            handle,
            amp=np.asarray(basis.amp, np.float32),
            phase=np.asarray(basis.phase, np.float32),
            knots=np.asarray(basis.knots, np.int32),
            amp_eigenvalues=info.amp_eigenvalues,
            phase_eigenvalues=info.phase_eigenvalues,
            amp_support_fraction=info.amp_support_fraction,
            phase_support_fraction=info.phase_support_fraction,
            meta=np.array(json.dumps(meta)),
        )


def read_basis(path: Path) -> tuple[LatentBasis, BasisInfo]:
    """Read a file written by :func:`save_basis`."""
    with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f["meta"]))
        grid = UVGrid(int(meta["n_knots"]), float(meta["spacing_m"]))
        basis = LatentBasis(
            amp=jnp.asarray(f["amp"]),
            phase=jnp.asarray(f["phase"]),
            knots=tuple(int(k) for k in f["knots"]),
            grid=grid,
        )
        info = BasisInfo(
            filter_name=meta["filter"],
            key=meta["key"],
            amp_eigenvalues=f["amp_eigenvalues"],
            phase_eigenvalues=f["phase_eigenvalues"],
            amp_support_fraction=f["amp_support_fraction"],
            phase_support_fraction=f["phase_support_fraction"],
            n_amp=int(meta["n_amp"]),
            n_phase=int(meta["n_phase"]),
            n_knots_used=int(meta["n_knots_used"]),
            n_knots_support=int(meta["n_knots_support"]),
            seconds=float(meta["seconds"]),
        )
    return basis, info


def _shipped(name: str) -> Path | None:
    try:
        candidate = resources.files("amigo") / "data" / "bases" / name
    except (ModuleNotFoundError, FileNotFoundError):
        return None
    return Path(str(candidate)) if candidate.is_file() else None


def load_basis(
    instrument: Instrument,
    filter_name: str,
    grid: UVGrid | None = None,
    *,
    build: bool = True,
) -> tuple[LatentBasis, BasisInfo]:
    """The basis of ``filter_name``: shipped, else cached, else built (and cached).

    Raises ``FileNotFoundError`` when it does not exist and ``build`` is False.
    """
    grid = UVGrid() if grid is None else grid
    key = basis_key(instrument, filter_name, grid)
    name = _file_name(filter_name, key)
    for candidate in (_shipped(name), cache_dir() / name):
        if candidate is not None and candidate.is_file():
            try:
                return read_basis(candidate)
            except Exception:  # any damage to a cache file: build it again
                step(f"basis cache {candidate} is unreadable: rebuilding it")
                break
    if not build:
        raise FileNotFoundError(f"no cached basis for {filter_name} (key {key})")
    step(f"building the {filter_name} visibility basis (cached afterwards in {cache_dir()})")
    basis, info = build_basis(instrument, filter_name, grid)
    try:
        save_basis(cache_dir() / name, basis, info)
    except OSError as error:  # a read-only home must not stop a fit
        step(f"could not cache the basis ({error})")
    # The basis as the cache holds it (float32): a fit must not depend on whether its
    # basis was built in this process or read back, or a re-run's products would differ
    # in their last bits from an uninterrupted run's.
    stored = LatentBasis(
        amp=jnp.asarray(np.asarray(basis.amp, np.float32)),
        phase=jnp.asarray(np.asarray(basis.phase, np.float32)),
        knots=basis.knots,
        grid=basis.grid,
    )
    return stored, info
