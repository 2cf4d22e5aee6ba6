"""amigo's optical propagation against dLux's (and poppy's): does dLux earn its place?

    pip install -e ".[peers]"   # dLux is no dependency of amigo any more
    python benchmarks/dlux.py [--repeats 100]

amigo imported three small dLux utilities (``cart2polar``, ``eval_radial`` and
``eval_azimuthal``, in :func:`amigo.model.optics.aperture.zernike_basis`) and now writes
them out itself; its propagation (:mod:`amigo.model.optics.propagation`) is its own. This
script measures, on one pupil, what dLux's propagation would give instead, and checks that
amigo's Zernike basis is dLux's.

The pupil is amigo's own (float64): the shipped :class:`OpticsConfig` (128 pupil pixels
across 6.6 m, cropped to the mask; a 240 x 240 focal grid of pitch 65.6 mas / 3), with
random Zernikes (20 nm rms per coefficient) so that the phase is not trivial. The same
amplitude and OPD arrays, embedded in the full 128 x 128 grid centred on the optical axis
(dLux and poppy take a square, centred pupil), are propagated by

* amigo: :meth:`NRMOptics.psfs` (the real-arithmetic :func:`propagation.mft_symmetric` on
  the cropped grid), the reference;
* dLux's ``utils.MFT`` (its matrix Fourier transform);
* dLux's ``AngularOpticalSystem`` with one ``Optic`` layer (what dLux is for);
* poppy's ``matrix_dft`` (``SYMMETRIC`` centring; poppy's transform has the opposite sign in
  its exponent, which mirrors the field through the centre: it is flipped back).

All are brought to amigo's normalisation with known factors, nothing fitted: the MFTs
with ``|E|^2 / P`` (``P`` amigo's pupil power), dLux's normalised system with
``sum(A^2) / P``.

Speed rows time the kernel "amplitude, OPD, wavelength -> point-sampled PSF" (the
phasor, the transform, the intensity), jitted, per monochromatic PSF: the first call
(compilation included, after ``jax.clear_caches``) and the warm minimum over
``--repeats`` calls, for the PSF and for the gradient of a scalar of it with respect to
the OPD (what a fit needs), in float32 and float64. poppy runs in NumPy (float64, no
gradient). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import os
import platform
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import jax.numpy as jnp
import numpy as np
from packaging.requirements import Requirement

jax.config.update("jax_enable_x64", True)
# dLux asks for float64 where the float32 rows switch 64-bit types off: JAX truncates (and says so).
warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")

import dLux as dl  # noqa: E402
import dLux.utils as dlu  # noqa: E402

from amigo import niriss  # noqa: E402
from amigo.model.optics import NRMOptics, OpticsConfig, propagation  # noqa: E402
from amigo.model.optics.aperture import _zernike_factors, zernike_basis  # noqa: E402
from amigo.model.optics.model import ARCSEC_TO_RAD  # noqa: E402
from code_lines import code_lines  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WAVELENGTHS_M = (3.8e-6, 4.8e-6)
ZERNIKE_RMS_NM = 20.0


# ------------------------------------------------------------------------------ the pupil
def amigo_pupil(config: OpticsConfig):
    """amigo's optics (float64, random Zernikes), its pupil on the cropped grid, and the
    same pupil embedded in the full square grid centred on the axis."""
    rng = np.random.default_rng(0)
    zernikes = jnp.asarray(rng.normal(0.0, ZERNIKE_RMS_NM, (7, config.n_zernike)))
    optics = NRMOptics.create(config, zernikes_nm=zernikes)
    amplitude, opd = (np.asarray(a, np.float64) for a in optics.pupil())
    power = float(optics.pupil_power())
    grid = optics.grid
    n, pixel = config.pupil_npix, grid.pixel_m
    axis = (np.arange(n) - 0.5 * (n - 1)) * pixel
    i0 = round(float(grid.y_m[0]) / pixel + 0.5 * (n - 1))
    j0 = round(float(grid.x_m[0]) / pixel + 0.5 * (n - 1))
    ny, nx = amplitude.shape
    # The cropped grid is a block of the full one (same lattice): checked, not assumed.
    assert np.allclose(axis[i0 : i0 + ny], grid.y_m, atol=1e-12 * n * pixel)
    assert np.allclose(axis[j0 : j0 + nx], grid.x_m, atol=1e-12 * n * pixel)
    full_amplitude, full_opd = np.zeros((n, n)), np.zeros((n, n))
    full_amplitude[i0 : i0 + ny, j0 : j0 + nx] = amplitude
    full_opd[i0 : i0 + ny, j0 : j0 + nx] = opd
    return optics, (amplitude, opd), (full_amplitude, full_opd), power


# ------------------------------------------------------------------------------ kernels
def kernels(optics: NRMOptics, config: OpticsConfig, power: float):
    """``name -> (psf(amplitude, opd, wavelength), cropped?)``: each returns the
    point-sampled PSF in amigo's normalisation."""
    grid = optics.grid
    pixel_rad = config.psf_pixel_rad
    m, half = config.npix_psf, config.npix_psf // 2
    n_full = config.pupil_npix

    def amigo_symmetric(amplitude, opd, wavelength):
        dtype = amplitude.dtype
        x, y = grid.x_m.astype(dtype), grid.y_m.astype(dtype)
        theta = propagation.centred_axis(m, pixel_rad, dtype=dtype)[half:]
        phase = (2.0 * jnp.pi / wavelength) * opd
        re, im = amplitude * jnp.cos(phase), amplitude * jnp.sin(phase)
        e_re, e_im = propagation.mft_symmetric(re, im, x, y, wavelength, theta, theta)
        norm = grid.pixel_m * pixel_rad / wavelength
        return (e_re**2 + e_im**2) * norm**2 / power

    def amigo_complex(amplitude, opd, wavelength):
        dtype = amplitude.dtype
        x, y = grid.x_m.astype(dtype), grid.y_m.astype(dtype)
        theta = propagation.centred_axis(m, pixel_rad, dtype=dtype)
        field = amplitude * jnp.exp((2j * jnp.pi / wavelength) * opd)
        e = propagation.mft(field, x, y, wavelength, theta, theta)
        norm = grid.pixel_m * pixel_rad / wavelength
        return (e.real**2 + e.imag**2) * norm**2 / power

    def dlux_mft(amplitude, opd, wavelength):
        field = amplitude * jnp.exp((2j * jnp.pi / wavelength) * opd)
        e = dlu.MFT(field, wavelength, grid.pixel_m, m, pixel_rad)
        return jnp.abs(e) ** 2 / power

    def dlux_system(amplitude, opd, wavelength):
        system = dl.AngularOpticalSystem(
            wf_npixels=n_full,
            diameter=n_full * grid.pixel_m,
            layers=[("pupil", dl.Optic(transmission=amplitude, opd=opd, normalise=True))],
            psf_npixels=config.npix_detector,
            psf_pixel_scale=config.pixel_scale_arcsec,
            oversample=config.oversample,
        )
        return system.propagate_mono(wavelength) * jnp.sum(amplitude**2) / power

    return {
        "amigo mft_symmetric (real, cropped)": (amigo_symmetric, True),
        "amigo mft (complex, cropped)": (amigo_complex, True),
        "dLux utils.MFT (square grid)": (dlux_mft, False),
        "dLux AngularOpticalSystem + Optic": (dlux_system, False),
    }


def poppy_psf(amplitude, opd, wavelength, config: OpticsConfig, pixel_m: float, power: float):
    """poppy's MFT of the full square pupil, flipped to amigo's sign convention."""
    from poppy.matrixDFT import SYMMETRIC, matrix_dft

    n = amplitude.shape[0]
    field = amplitude * np.exp((2j * np.pi / wavelength) * opd)
    n_lambda_d = config.npix_psf * config.psf_pixel_rad / (wavelength / (n * pixel_m))
    e = matrix_dft(field, n_lambda_d, config.npix_psf, centering=SYMMETRIC)
    return (np.abs(e) ** 2 / power)[::-1, ::-1]


# ------------------------------------------------------------------------------ timing
def timed(function, args, repeats: int) -> tuple[float, float, float]:
    """(first call s, compilation included; warm minimum s; warm median s)."""
    jax.clear_caches()
    start = time.perf_counter()
    jax.block_until_ready(function(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*args))
        times.append(time.perf_counter() - start)
    return first, min(times), statistics.median(times)


def gradient_of(psf, weights):
    """d/dOPD of ``sum(w * psf)``: the reverse pass a fit pays per PSF."""
    return jax.grad(
        lambda opd, amplitude, wavelength: jnp.sum(weights * psf(amplitude, opd, wavelength))
    )


# ------------------------------------------------------------------------------ Zernikes
def dlux_zernike_basis(grid, centres_m, radius_m, n_modes, support_m):
    """The per-hole Zernike basis as amigo built it with dLux's three utilities (polar
    coordinates, the radial sum, the azimuthal factor), before it wrote them out."""
    x, y = grid.coordinates()
    factors = [_zernike_factors(j) for j in range(1, n_modes + 1)]

    def one_hole(centre):
        rho, theta = dlu.cart2polar(jnp.stack([x - centre[0], y - centre[1]]) / radius_m)
        inside = rho * radius_m <= support_m
        return jnp.stack(
            [
                inside
                * dlu.eval_radial(rho, n, c.astype(rho.dtype), k.astype(rho.dtype))
                * dlu.eval_azimuthal(theta, n, m)
                for n, m, c, k in factors
            ]
        )

    return jax.vmap(one_hole)(jnp.asarray(centres_m))


# ------------------------------------------------------------------------------ footprint
def _requirements(name: str) -> list[str]:
    """Run-time requirements of an installed distribution on this platform (no extras)."""
    out = []
    for text in metadata.requires(name) or []:
        requirement = Requirement(text)
        if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
            out.append(requirement.name)
    return out


def _closure(roots: list[str], dropped: str | None = None) -> set[str]:
    """Installed distributions a ``pip install`` of ``roots`` pulls in, optionally with
    the requirement ``dropped`` removed from the first level."""
    seen: set[str] = set()
    stack = [r for r in roots if r.lower() != (dropped or "").lower()]
    while stack:
        name = stack.pop().lower()
        if name in seen:
            continue
        seen.add(name)
        try:
            stack.extend(_requirements(name))
        except metadata.PackageNotFoundError:
            pass
    return seen


def _installed_bytes(name: str) -> int:
    dist = metadata.distribution(name)
    return sum(f.size or 0 for f in dist.files or [])


def import_seconds(statement: str, before: str, repeats: int = 3) -> float:
    """Best wall time of ``statement`` in a fresh interpreter after ``before`` ran."""
    code = (
        f"import time\n{before}\nt = time.perf_counter()\n{statement}\n"
        "print(time.perf_counter() - t)"
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    best = np.inf
    for _ in range(repeats):
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
        )
        best = min(best, float(out.stdout.strip().splitlines()[-1]))
    return best


# ------------------------------------------------------------------------------ main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=100)
    args = parser.parse_args()
    config = OpticsConfig()
    optics, (amplitude, opd), (full_amplitude, full_opd), power = amigo_pupil(config)
    rows = kernels(optics, config, power)
    print(
        f"\nmachine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores; "
        f"JAX {jax.__version__} on {jax.default_backend()}, dLux {metadata.version('dLux')}, "
        f"poppy {metadata.version('poppy')}"
    )
    print(
        f"pupil: {config.pupil_npix} px across {config.pupil_diameter_m} m, cropped to "
        f"{amplitude.shape[0]} x {amplitude.shape[1]} (amigo) / {config.pupil_npix} x "
        f"{config.pupil_npix} (dLux, poppy); focal grid {config.npix_psf} x {config.npix_psf} "
        f"at {config.psf_pixel_rad / ARCSEC_TO_RAD * 1e3:.2f} mas"
    )

    # ---------------------------------------------------------------- accuracy
    print("\nAccuracy (float64), max |PSF - amigo NRMOptics.psfs| / amigo peak:")
    reference = np.asarray(optics.psfs(jnp.asarray(WAVELENGTHS_M), jnp.zeros(2)))
    header = f"{'propagation':40s}" + "".join(f"{w * 1e6:>12.1f} um" for w in WAVELENGTHS_M)
    print(header)
    for name, (psf, cropped) in rows.items():
        pupil = (amplitude, opd) if cropped else (full_amplitude, full_opd)
        function = jax.jit(psf)
        errors = [
            np.max(np.abs(np.asarray(function(*map(jnp.asarray, pupil), w)) - ref)) / ref.max()
            for w, ref in zip(WAVELENGTHS_M, reference, strict=True)
        ]
        print(f"{name:40s}" + "".join(f"{e:15.2e}" for e in errors))
    try:
        errors = [
            np.max(
                np.abs(
                    poppy_psf(full_amplitude, full_opd, w, config, optics.grid.pixel_m, power) - ref
                )
            )
            / ref.max()
            for w, ref in zip(WAVELENGTHS_M, reference, strict=True)
        ]
        print(f"{'poppy matrix_dft (NumPy)':40s}" + "".join(f"{e:15.2e}" for e in errors))
    except ImportError:
        print("poppy matrix_dft: poppy is not installed (test extra)")

    # ---------------------------------------------------------------- speed
    print(
        f"\nSpeed per monochromatic PSF at {WAVELENGTHS_M[1] * 1e6:.1f} um (ms; first call "
        f"includes compilation; warm = minimum of {args.repeats}, median in brackets):"
    )
    print(
        f"{'propagation':40s} {'PSF out':>7s} {'PSF first':>10s} {'PSF warm':>17s} "
        f"{'grad first':>11s} {'grad warm':>17s}"
    )
    weights = jnp.asarray(np.random.default_rng(1).uniform(size=(config.npix_psf,) * 2))
    for name, (psf, cropped) in rows.items():
        pupil = (amplitude, opd) if cropped else (full_amplitude, full_opd)
        for dtype in (jnp.float32, jnp.float64):
            # float32 as amigo's fits run it: with 64-bit types switched off (dLux, whose
            # coordinates are built as Python floats, would otherwise compute in float64).
            with jax.enable_x64(dtype == jnp.float64):
                a, o = (jnp.asarray(p, dtype) for p in pupil)
                wavelength = jnp.asarray(WAVELENGTHS_M[1], dtype)
                w = jnp.asarray(weights, dtype)
                forward = timed(jax.jit(psf), (a, o, wavelength), args.repeats)
                backward = timed(jax.jit(gradient_of(psf, w)), (o, a, wavelength), args.repeats)
                out = jax.jit(psf)(a, o, wavelength).dtype
            print(
                f"{name:40s} {np.dtype(out).name:>7s} {1e3 * forward[0]:10.0f} "
                f"{1e3 * forward[1]:8.2f} [{1e3 * forward[2]:6.2f}] {1e3 * backward[0]:11.0f} "
                f"{1e3 * backward[1]:8.2f} [{1e3 * backward[2]:6.2f}]"
            )
    try:
        pixel_m = optics.grid.pixel_m
        times = []
        for _ in range(max(3, args.repeats // 4)):
            start = time.perf_counter()
            poppy_psf(full_amplitude, full_opd, WAVELENGTHS_M[1], config, pixel_m, power)
            times.append(time.perf_counter() - start)
        print(
            f"{'poppy matrix_dft (NumPy)':40s} {'float64':>7s} {'':>10s} {1e3 * min(times):8.2f} "
            f"[{1e3 * statistics.median(times):6.2f}] {'(no gradient)':>11s}"
        )
    except ImportError:
        pass

    # ---------------------------------------------------------------- Zernike utilities
    grid = optics.grid
    centres = niriss.HOLE_CENTRES_M
    radius = config.zernike_radius_factor * niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3.0)
    support = 0.66
    own = np.asarray(jax.jit(lambda: zernike_basis(grid, centres, radius, 21, support))())
    with_dlux = np.asarray(
        jax.jit(lambda: dlux_zernike_basis(grid, centres, radius, 21, support))()
    )
    print(
        "\nZernike basis (7 holes x 21 Noll modes on the pupil grid, float64): "
        f"max |amigo - dLux-built| = {np.max(np.abs(own - with_dlux)):.1e} "
        f"(mode values up to {np.max(np.abs(with_dlux)):.1f})"
    )

    # ---------------------------------------------------------------- lines and footprint
    src = ROOT / "src" / "amigo" / "model" / "optics"
    dlux_root = Path(dl.__file__).parent
    used = {
        "cart2polar": dlux_root / "utils" / "coordinates.py",
        "eval_radial": dlux_root / "utils" / "zernikes.py",
        "eval_azimuthal": dlux_root / "utils" / "zernikes.py",
    }
    print("\nLines of code (no blanks, comments or docstrings):")
    print(
        f"  amigo mft + mft_symmetric: {code_lines(src / 'propagation.py', 'mft')} + "
        f"{code_lines(src / 'propagation.py', 'mft_symmetric')}"
    )
    basis_lines = sum(
        code_lines(src / "aperture.py", name) for name in ("zernike_basis", "_radial", "_azimuthal")
    )
    print(f"  amigo zernike_basis with its own _radial and _azimuthal: {basis_lines}")
    print(
        "  dLux functions amigo calls: "
        + ", ".join(f"{name} {code_lines(path, name)}" for name, path in used.items())
    )
    dlux_mft = sum(
        code_lines(dlux_root / "utils" / "propagation.py", name)
        for name in ("MFT", "transfer_matrix", "calc_nfringes")
    )
    print(f"  dLux MFT (with transfer_matrix, calc_nfringes): {dlux_mft}")

    amigo_deps = _closure(_requirements("amigo-jwst"))
    gone = sorted(_closure(["dLux"]) - amigo_deps)
    size = sum(_installed_bytes(name) for name in gone)
    print(
        f"\nWhat dLux would add to amigo's run-time install: {', '.join(gone)} "
        f"({size / 1e6:.2f} MB installed)"
    )
    extra = import_seconds("import dLux", "import jax, equinox, optax, numpy")
    print(f"import dLux after jax, equinox, optax: {extra:.2f} s (best of 3 fresh interpreters)")


if __name__ == "__main__":
    main()
