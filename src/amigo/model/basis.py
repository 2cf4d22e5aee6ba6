"""Latent visibility bases: build, truncate, cache (the paper's "Latent Visibility Model").

For one filter and one instrument state:

1. ``J``: the Jacobian of the 80 x 80 image of a centred unit-flux point source with
   respect to the free log-amplitudes and phases of the knot grid, at ``V = 1``, only for
   the knots whose interpolation footprint touches the OTF (the others have zero
   columns). It is the fit's own image (:func:`amigo.model.image.jittered_illuminance`:
   the visibilities' band to the image in two matrix products per column) linearised
   once and applied to the unit tangents in batches (:func:`amigo.model.columns.columns_of`,
   as the fit's Jacobians are); the tests hold it against forward-mode differentiation
   of the plain path through the FFTs (:func:`amigo.model.image.illuminance_from_psfs`,
   then the detector). On two CPU cores a filter's 2 x 1300 columns take 1.3 s this way;
   format 2 took 4.5 s differentiating the same image batch by batch, its forward pass
   evaluated again for every batch of 16 columns.
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
``amigo/data/bases`` (none: a basis of the default grid is 5.3 MB per filter, compressed)
are found the same way. A build of the default grid takes 3-4 s per filter on two CPU
cores once its program is compiled (the first build in a fresh cache: ~8 s per filter,
three filters 25 s within a cold ``amigo fit``, against 37 s with format 2).
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
from amigo.model.columns import columns_of
from amigo.model.image import (
    FilterSetup,
    Instrument,
    OpticsParams,
    filter_psfs,
    jittered_illuminance,
)
from amigo.model.visibility import LatentBasis, UVGrid
from amigo.progress import step

#: Version of the basis algorithm and file layout (part of the cache key). 3: the
#: Jacobian linearised once (equal to format 2's to float32 rounding, but eigenvectors of
#: near-equal eigenvalues may turn: a new key, so that one installation never mixes
#: bases of both) and the MTF in float64.
BASIS_FORMAT = 3
#: MTF level that bounds the OTF support (see module notes).
SUPPORT_MTF = 1e-3
#: A mode is kept while at least this fraction of its energy lies inside the support.
MIN_SUPPORT_FRACTION = 0.5
#: A knot is computed when its footprint sees at least this fraction of the peak OTF.
TOUCH_FRACTION = 1e-8


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
    # float64 throughout (a JAX float32 wavelength would make the phases float32).
    wavelengths = np.asarray(wavelengths_m, np.float64)
    for psf, w, wl in zip(psfs, weights, wavelengths, strict=True):
        ex = np.exp(-2j * np.pi * np.outer(uv_m[:, 0] / wl, theta))
        ey = np.exp(-2j * np.pi * np.outer(uv_m[:, 1] / wl, theta))
        # sum_yx ey[k, y] psf[y, x] ex[k, x]: one matrix product, then a row-wise dot
        # (the three-way einsum took 1.5 s a filter: it is not dispatched to BLAS).
        out += w * np.abs(np.sum((ey @ psf) * ex, axis=1)) / psf.sum()
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
def knot_jacobian(
    instrument: Instrument, setup: FilterSetup, psfs: jax.Array, knots: jax.Array
) -> jax.Array:
    """(2 k, 80, 80) Jacobian of the centred unit-flux point source's image (flat SED, the
    instrument's jitter, PSFs ``psfs`` centred) w.r.t. the log-amplitudes, then the
    phases, of the free knots ``knots`` (k,) at ``V = 1`` (see module notes)."""
    dtype = setup.injector.w_y.dtype
    n_half, k = setup.grid.n_half, knots.shape[0]
    jitter_arcsec = instrument.detector.jitter_arcsec.astype(dtype)
    zero = jnp.zeros((), dtype)

    def image(values):
        log_amp = jnp.zeros(n_half, dtype).at[knots].set(values[:k])
        phase = jnp.zeros(n_half, dtype).at[knots].set(values[k:])
        log_amp, phase = setup.grid.to_full(log_amp, phase)
        blurred = jittered_illuminance(
            instrument, setup, psfs, zero, jnp.zeros(2, dtype), log_amp, phase, None,
            jitter_arcsec,
        )  # fmt: skip
        return instrument.detector.after_jitter(blurred, 1.0)

    return columns_of(image, jnp.zeros(2 * k, dtype), (k,))


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
    if len(knots) == 0:
        raise ValueError(f"basis {filter_name}: no knot of the grid reaches the OTF")
    step(f"basis {filter_name}: {len(knots)} of {grid.n_half} knots reach the OTF")
    step(f"basis {filter_name}: Jacobian of the knots")
    jac = np.asarray(knot_jacobian(instrument, setup, psfs, jnp.asarray(knots)), np.float64)
    jac = jac.reshape(2, len(knots), -1)
    j_amp, j_pha = jac[0].T, jac[1].T
    del jac
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
