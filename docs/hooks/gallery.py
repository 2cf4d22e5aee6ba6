"""mkdocs hook: the figures of docs/gallery.md, drawn when the site is built.

Figures are generated output and are never committed. While mkdocs renders the pages,
this file runs as a script in two more processes, which draw every figure with amigo's
own plotting functions (:mod:`amigo.plots`) on small synthetic inputs into a temporary
folder; the hook lists the PNG files among the site's
files (so the links of gallery.md are checked like any other) and waits for the drawing
to finish before mkdocs copies them into the site. A figure that fails to draw fails the
build: the gallery is a test that amigo's plotting functions still work.

Run alone to look at the figures: ``python docs/hooks/gallery.py OUT_DIR [PART...]``.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

#: The PNG files gallery.md shows, under ``gallery/`` in the site.
FIGURES = (
    "pupil.png",
    "psf.png",
    "power_spectrum.png",
    "residuals.png",
    "basis_spectrum.png",
    "detection_maps.png",
    "contrast_limits.png",
    "posterior_predictive.png",
    "corner.png",
    "loss_curve.png",
)

#: The drawing functions below, in two processes of about the same length (with mkdocs
#: itself, they keep two cores busy).
PARTS = (("_loss_figure", "_optics_figures", "_basis_figure"), ("_companion_figures",))

# ---------------------------------------------------------------------------- the hook
_state: dict[str, object] = {}
_log = logging.getLogger("mkdocs.hooks.gallery")


def on_pre_build(config) -> None:
    """Start drawing the figures: two processes (see :data:`PARTS`)."""
    out = Path(tempfile.mkdtemp(prefix="amigo-gallery-"))
    env = dict(os.environ, JAX_PLATFORMS="cpu", MPLBACKEND="Agg")
    jobs = []
    for k, parts in enumerate(PARTS):
        log = open(out / f"gallery{k}.log", "w+")  # closed in on_env
        command = [sys.executable, __file__, str(out), *parts]
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
        jobs.append((process, log))
    _state.update(out=out, jobs=jobs, start=time.perf_counter())


def on_files(files, config):
    """List the figures among the site's files (drawn by then or not: they are copied
    after the pages are rendered)."""
    from mkdocs.structure.files import File

    out = _state["out"]
    for name in FIGURES:
        files.append(
            File.generated(config, f"gallery/{name}", abs_src_path=os.fspath(Path(out) / name))
        )
    return files


def on_env(env, config, files):
    """Wait for the figures (mkdocs copies the files next); any failure fails the build."""
    from mkdocs.exceptions import PluginError

    out = Path(_state["out"])
    codes, text = [], ""
    for process, log in _state.pop("jobs"):
        codes.append(process.wait())
        log.seek(0)
        text += log.read()
        log.close()
    missing = [name for name in FIGURES if not (out / name).is_file()]
    if any(codes) or missing:
        raise PluginError(
            f"gallery: drawing the figures failed (exit status {codes}, missing {missing}):\n"
            + text[-4000:]
        )
    seconds = time.perf_counter() - float(_state["start"])
    _log.info(f"gallery: {len(FIGURES)} figures drawn in {seconds:.1f} s")
    return env


def on_post_build(config) -> None:
    """Remove the temporary folder (its files are in the site now)."""
    out = _state.pop("out", None)
    if out is not None:
        shutil.rmtree(out, ignore_errors=True)


def on_build_error(error) -> None:
    """Stop the drawing processes of a build that failed elsewhere, and clean up."""
    for process, log in _state.pop("jobs", []):
        if process.poll() is None:
            process.kill()
            process.wait()
        log.close()
    on_post_build(None)


# ------------------------------------------------------------------------ the figures
def _optics_figures(out: Path) -> None:
    """Pupil, PSF, power spectrum and a fit's residual figure from the optical model."""
    import jax.numpy as jnp
    import numpy as np

    from amigo.likelihood.pixels import ImageData
    from amigo.model.detector.linear import LinearDetector
    from amigo.model.optics import NRMOptics, OpticsConfig, PointSource
    from amigo.observables.extract import ExposureStats
    from amigo.plots import fit as fit_plots
    from amigo.plots import optics as optics_plots

    config = OpticsConfig()
    rng = np.random.default_rng(1)
    # A telescope with 15 nm rms of random per-hole Zernike aberrations (piston to Z10).
    zernikes = jnp.asarray(rng.normal(0.0, 15.0, (7, config.n_zernike)))
    aberrated = NRMOptics.create(config, zernikes_nm=zernikes)
    nominal = NRMOptics.create(config)
    source = PointSource.create("F430M", n_wavelengths=5)
    scale = config.pixel_scale_arcsec / config.oversample
    image = np.asarray(aberrated.illuminance(source.spectrum, source.position_arcsec))
    for name, fig in (
        ("pupil.png", optics_plots.pupil_figure(aberrated)),
        ("psf.png", optics_plots.psf_figure(image, scale, "F430M PSF (3x oversampled)")),
        ("power_spectrum.png", optics_plots.power_spectrum_figure(image, scale, 4.3e-6)),
    ):
        optics_plots.save(fig, out / name, dpi=80)

    # "Data": the aberrated telescope through the linear detector, with photon and read
    # noise; "model": the unaberrated one. The residuals show the missing wavefront.
    detector = LinearDetector.create()
    flux = 2.0e5  # DN/s
    truth = np.asarray(detector(jnp.asarray(image), flux), dtype=float)
    model_3x = nominal.illuminance(source.spectrum, source.position_arcsec)
    model = np.asarray(detector(model_3x, flux), dtype=float)
    error = np.sqrt(np.clip(truth, 0.0, None) / 10.0 + 4.0)
    data = truth + error * rng.normal(size=truth.shape)
    mask = np.ones(data.shape, dtype=bool)
    mask[:4] = False  # the reference rows of SUB80
    exposure = ImageData(data=data, error=error, mask=mask)
    z = ((data - model) / error)[mask]
    stats = ExposureStats(
        name="synthetic_cal.fits",
        role="science",
        target="SYNTHETIC",
        filter="F430M",
        npix=int(mask.sum()),
        chi2=float(np.sum(z**2)),
        dof=float(mask.sum()),
        zscore_std=float(np.std(z)),
        zscore_std_whitened=float(np.std(z)),  # no stripes in this image
        converged=True,
        iterations=0,
        seconds=0.0,
    )
    fit_plots.save_figure(fit_plots.exposure_figure(exposure, model, stats), out / "residuals.png")


def _basis_figure(out: Path) -> None:
    """The eigenvalue spectra of a latent visibility basis, on a coarse uv grid."""
    from amigo.model.basis import build_basis
    from amigo.model.detector.linear import LinearDetector
    from amigo.model.image import Instrument
    from amigo.model.optics import NRMOptics, OpticsConfig
    from amigo.model.visibility import UVGrid
    from amigo.plots import optics as optics_plots
    from amigo.plots.basis import spectrum_figure

    instrument = Instrument(
        optics=NRMOptics.create(OpticsConfig(pupil_npix=64)),
        detector=LinearDetector.create(),
        n_wavelengths=3,
        name="gallery (nominal, coarse)",
    )
    _, info = build_basis(instrument, "F430M", UVGrid(n_knots=11, spacing_m=1.3))
    optics_plots.save(spectrum_figure(info), out / "basis_spectrum.png", dpi=80)


def _kernel_matrix(n_holes: int, pairs) -> tuple[object, int]:
    """Rows that null hole gains (amplitudes) and hole pistons (phases) of log V at the
    baselines: the kernel amplitudes and phases of a perfect mask."""
    import numpy as np

    pairs = np.asarray(pairs)
    n_b = len(pairs)
    gains = np.zeros((n_b, n_holes))
    pistons = np.zeros((n_b, n_holes))
    rows = np.arange(n_b)
    gains[rows, pairs[:, 0]] = gains[rows, pairs[:, 1]] = 1.0
    pistons[rows, pairs[:, 0]], pistons[rows, pairs[:, 1]] = -1.0, 1.0

    def left_null(matrix):
        u, s, _ = np.linalg.svd(matrix, full_matrices=True)
        return u[:, int(np.sum(s > 1e-10 * s.max())) :].T

    k_amp, k_phase = left_null(gains), left_null(pistons)
    matrix = np.zeros((len(k_amp) + len(k_phase), 2 * n_b))
    matrix[: len(k_amp), :n_b] = k_amp
    matrix[len(k_amp) :, n_b:] = k_phase
    return matrix, len(k_amp)


def _companion_figures(out: Path) -> None:
    """Detection maps, contrast limits, posterior predictive check and a corner plot of a
    simulated binary in two filters (least squares; no NUTS, to stay quick)."""
    import jax
    import numpy as np

    from amigo import niriss
    from amigo.companions import observables
    from amigo.companions.models import scene_visibility
    from amigo.companions.search import SearchSettings, detect
    from amigo.io.calvis import CalVis, nominal_sky_to_uv
    from amigo.orientation import Orientation, separation_pa
    from amigo.plots import companions as plots
    from amigo.plots import optics as optics_plots

    rng = np.random.default_rng(3)
    matrix, n_amp = _kernel_matrix(niriss.N_HOLES, niriss.baseline_pairs())
    kinds = ("amplitude",) * n_amp + ("phase",) * (matrix.shape[0] - n_amp)
    uv = niriss.baselines_m()
    orientation = Orientation(pa_aper_deg=120.0)
    sky_to_uv = nominal_sky_to_uv(orientation)
    offset = np.array([[250.0, -120.0]])  # dRA, dDec (mas)
    blocks = []
    with jax.enable_x64(True):
        for filter_name, ratio in (("F380M", 0.020), ("F480M", 0.025)):
            bins = niriss.filter_bins(filter_name, 5)
            vis = np.asarray(
                scene_visibility(
                    uv @ sky_to_uv, bins.wavelengths_m, bins.weights, offset, np.array([ratio])
                )
            )
            log_vis = np.concatenate([np.log(np.abs(vis)), np.angle(vis)])
            errors = np.full(matrix.shape[0], 3e-3)
            calvis = CalVis(
                values=matrix @ log_vis + errors * rng.normal(size=errors.size),
                errors=errors,
                kinds=kinds,
                disco_matrix=matrix,
                uv_m=uv,
                wavelengths_m=np.asarray(bins.wavelengths_m),
                weights=np.asarray(bins.weights),
                sky_to_uv=sky_to_uv,
                orientation=orientation,
                n_photons=1e9,
                target="SYNTHETIC",
                filter_name=filter_name,
            )
            blocks.append(observables.from_calvis(calvis, source=filter_name))
        dataset = observables.Dataset.from_blocks(blocks)
        settings = SearchSettings(rmax_mas=400.0, max_companions=1, hmc=False, per_filter=False)
        result = detect(dataset, settings)
        plots.plot_detection_maps(result, out / "detection_maps.png")
        plots.plot_contrast_limits(result, out / "contrast_limits.png")
        plots.plot_posterior_predictive(result, out / "posterior_predictive.png")

    # Corner plot of draws from the least-squares fit's Laplace covariance (amigo detect
    # draws one per companion from the NUTS posterior, which takes longer).
    fit = result.fit
    mean = np.concatenate([fit.offsets_mas.ravel(), fit.log10_contrasts.ravel()])
    draws = rng.multivariate_normal(mean, fit.covariance, size=4000)
    sep, pa = separation_pa(draws[:, 0], draws[:, 1])
    columns = [sep, pa, *(-2.5 * draws[:, 2 + f] for f in range(len(dataset.filters)))]
    labels = ["sep (mas)", "PA (deg)", *(f"dmag {f}" for f in dataset.filters)]
    fig = plots.corner(np.column_stack(columns), labels)
    fig.suptitle("companion 1: Laplace approximation of the least-squares fit", fontsize=10)
    optics_plots.save(fig, out / "corner.png", dpi=80)


def _loss_figure(out: Path) -> None:
    """The layout of a training run's loss curve, on made-up numbers (the real one is
    drawn beside every model ``amigo train`` writes)."""
    import numpy as np

    from amigo.plots import optics as optics_plots
    from amigo.plots.training import loss_curve_figure

    rng = np.random.default_rng(0)
    steps = np.arange(60)
    stage = (steps >= 12).astype(int) + (steps >= 36).astype(int)
    loss = 0.5 + 40.0 * np.exp(-steps / 8.0) + 0.3 * np.exp(-(steps - 12).clip(0) / 10.0)
    loss = loss * np.exp(0.08 * rng.normal(size=steps.size))
    epochs = steps[4::5]
    history = SimpleNamespace(
        step=list(steps),
        stage=list(stage),
        loss=list(loss),
        epoch_step=list(epochs),
        cal_loss=list(loss.reshape(-1, 5).mean(axis=1)),
        val_loss=list(1.1 * loss.reshape(-1, 5).mean(axis=1) + 0.05),
    )
    fig = loss_curve_figure(history, "training loss (illustrative numbers)")
    optics_plots.save(fig, out / "loss_curve.png", dpi=80)


def draw(out: Path, parts: tuple[str, ...] = sum(PARTS, ())) -> None:
    """Draw the figures of ``parts`` (names of the functions above) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    for name in parts:
        start = time.perf_counter()
        globals()[name](out)
        print(f"{name}: {time.perf_counter() - start:.1f} s", flush=True)


if __name__ == "__main__":
    draw(Path(sys.argv[1]), tuple(sys.argv[2:]) or sum(PARTS, ()))
