"""Levenberg-Marquardt: amigo's two hand-written solvers against optimistix's, same problems.

    python benchmarks/solvers.py [--skip-companions] [--skip-image] [--image-zernikes 4]

amigo has two Levenberg-Marquardt solvers: the small one of the companion fits
(:func:`amigo.companions.fit.levenberg_marquardt`: residuals and Jacobian in one jitted
call, Marquardt's diagonal scaling, a host-side loop) and the image fits' one
(:func:`amigo.solvers.levenberg_marquardt.minimise`: Jacobi-scaled damped Gauss-Newton on
an externally assembled Fisher matrix, chord steps with fresh gradients only, float32
switched to float64 near the optimum). optimistix, already a dependency, ships
``optimistix.LevenbergMarquardt`` (``optimistix.least_squares``: a residual function, its
Jacobian by forward-mode JAX, a QR solve of the damped system each step, a trust region
on the damping).

(i) Companion fits. Calibrated observables of a binary are simulated by the tests' own
independent NumPy code (``tests/detect_helpers.py``: kernel amplitudes and phases of the
21 NIRISS baselines, each splodge sampled at 7 uv points, F380M and F480M, noise 2e-3) for
three binaries, 150-300 mas and 4-7 mag. Both solvers start from the same point (+5 and
-5 mas in dRA and dDec, +0.3 dex in contrast off the truth, as a grid peak would), on the
same residual function (:func:`amigo.companions.fit._flat_residual`), in float64. Reported:
the chi2 reached and its difference to the best of the two, the largest parameter
difference in units of the Laplace errors, residual+Jacobian evaluations, and wall times:
cold (``jax.clear_caches`` first: compilation included) and warm (best of three). Then a
whole detection (``detect``, no HMC) with each solver in a fresh process, as ``amigo
detect`` runs it (JAX's persistent compilation cache on), with an empty cache and again.

(ii) The image fit's solver, on a shrunk image fit: one calibrator exposure of F480M
(simulated with amigo's optics, 1e7 photons, Zernikes of 3 nm rms), 2 wavelengths instead
of 9, the 7 x 7 knot grid (17 + 17 latent modes) instead of 51 x 51, and
``--image-zernikes`` Zernikes per hole (10 in the shipped model; 4 by default here, to
keep the whole script within about four minutes on 2 cores). Parameters: position, flux,
slope, jitter, latents and the instrument block (Zernikes, defocus, geometry, band taper)
with its priors. amigo runs :func:`minimise` on the fit's own problem
(:class:`amigo.fitting.newton._Problem`) at its default tolerance (Newton decrement 1) and
a tight one (0.01); optimistix runs ``least_squares`` on the whitened residuals of the
packed parameter vector (the same model, priors as residuals, float64, Jacobian by JAX),
once on the raw vector (capped at a few steps: it is slow) and once Jacobi-scaled (the
vector multiplied by ``sqrt(diag F)`` at the start, which is what amigo's solver does
internally). Each optimistix step costs one full Jacobian (the QR solve materialises it):
there are no chord steps. optimistix's
cold time is its compilation (ahead of time) plus the run; warm is the run.

Lines of code are counted without blanks, comments and docstrings
(``benchmarks/code_lines.py``). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# No persistent compilation cache (cold means compiled here), except where detection()
# asks for one, as amigo's commands use it.
os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ.get("AMIGO_BENCH_XLA_CACHE", "")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the tests' independent simulation of observables

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

from amigo.companions import fit as companion_fit  # noqa: E402
from amigo.companions import observables  # noqa: E402
from amigo.fitting import newton  # noqa: E402
from amigo.solvers.levenberg_marquardt import minimise  # noqa: E402
from code_lines import code_lines  # noqa: E402

LOG10_PER_MAG = -0.4  # log10 flux ratio per magnitude
#: Binaries of part (i): (separation mas, position angle deg, contrast mag).
BINARIES = ((150.0, 40.0, 4.0), (220.0, 130.0, 5.5), (300.0, 250.0, 7.0))
COMPANION_TOLERANCE = 1e-6  # optimistix rtol = atol: reaches amigo's chi2 to ~1e-11
IMAGE_TOLERANCE = 1e-2  # optimistix rtol = atol in Jacobi-scaled units (sigma-like)
RAW_STEPS = 8  # optimistix steps on the unscaled image problem


def wall(function):
    """(result, seconds) of one call."""
    start = time.perf_counter()
    out = function()
    jax.block_until_ready(out)
    return out, time.perf_counter() - start


def table(title: str, header: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print(f"\n{title}")
    print(
        "  ".join(
            h.rjust(w) if i else h.ljust(w)
            for i, (h, w) in enumerate(zip(header, widths, strict=True))
        )
    )
    for row in rows:
        print(
            "  ".join(
                c.rjust(w) if i else c.ljust(w)
                for i, (c, w) in enumerate(zip(row, widths, strict=True))
            )
        )


# ------------------------------------------------------------------------ (i) companions
def companion_dataset(tmp: Path, separation: float, pa_deg: float, mag: float, seed: int):
    from detect_helpers import write_sim_calvis

    rng = np.random.default_rng(seed)
    dra = separation * np.sin(np.deg2rad(pa_deg))
    ddec = separation * np.cos(np.deg2rad(pa_deg))
    flux = 10.0 ** (LOG10_PER_MAG * mag)
    blocks = []
    for f in ("F380M", "F480M"):
        path = tmp / f"S{seed}_{f}_calvis.fits"
        write_sim_calvis(path, f, [(dra, ddec, flux)], rng, splodge_radius_m=0.35)
        blocks.append(observables.load(path))
    truth = np.array([dra, ddec, np.log10(flux), np.log10(flux)])
    return observables.Dataset.from_blocks(blocks), truth


@eqx.filter_jit
def optimistix_levenberg_marquardt(residuals, x0, data, rtol: float, max_steps: int = 200):
    """What would replace :func:`amigo.companions.fit.levenberg_marquardt`: the same
    ``(x, r, J, converged)`` from optimistix (the Jacobian at the optimum is the
    covariance's), compiled as one program."""
    solver: optx.LevenbergMarquardt = optx.LevenbergMarquardt(rtol=rtol, atol=rtol)
    solution: optx.Solution = optx.least_squares(
        residuals, solver, x0, data, max_steps=max_steps, throw=False
    )
    x = solution.value
    converged = solution.result == optx.RESULTS.successful
    return x, residuals(x, data), jax.jacfwd(residuals)(x, data), converged, solution.stats


def _flat_residual(y, args):
    """The companion fits' whitened residuals at the flat parameters ``[offsets.ravel(),
    log10c.ravel()]``: what :func:`amigo.companions.fit._residual_and_jacobian`
    differentiates block by block, in one vector."""
    dataset, scale_vectors, k, diameter = args
    offsets = y[: 2 * k].reshape(k, 2)
    log10c = jnp.clip(y[2 * k :], companion_fit.LOG10_CONTRAST_FLOOR, 0.0).reshape(k, -1)
    blocks = companion_fit.block_residuals(dataset, offsets, 10.0**log10c, diameter)
    return jnp.concatenate([r / scale for r, scale in zip(blocks, scale_vectors, strict=True)])


def _companion_residuals(y, data):
    return _flat_residual(y, (*data, 1, 0.0))


def companion_case(dataset, truth) -> tuple[list[str], list[str]]:
    """One binary: amigo's solver and optimistix's from the same start."""
    scales = dataset.scale_vectors(np.ones(dataset.n_groups))
    data = (dataset, scales)
    start = truth + np.array([5.0, -5.0, 0.3, 0.3])
    calls = [0]

    def function(y):
        calls[0] += 1
        return companion_fit._residual_and_jacobian(jnp.asarray(y), (*data, 1, 0.0))

    def amigo():
        return companion_fit.levenberg_marquardt(function, start)

    def optimistix():
        return optimistix_levenberg_marquardt(
            _companion_residuals, jnp.asarray(start), data, COMPANION_TOLERANCE
        )

    jax.clear_caches()
    (x_amigo, r_amigo, jac, _), cold_amigo = wall(amigo)
    calls[0] = 0
    warm_amigo = min(wall(amigo)[1] for _ in range(3))
    n_amigo = calls[0] // 3
    jax.clear_caches()
    (x_optx, r_optx, _, _, stats), cold_optx = wall(optimistix)
    warm_optx = min(wall(optimistix)[1] for _ in range(3))
    chi2_amigo, chi2_optx = float(r_amigo @ r_amigo), float(np.sum(np.asarray(r_optx) ** 2))
    best = min(chi2_amigo, chi2_optx)
    errors = np.sqrt(np.diag(np.linalg.pinv(jac.T @ jac, hermitian=True)))
    shift = np.max(np.abs(np.asarray(x_optx) - x_amigo) / errors)
    amigo_row = [
        "amigo LM", f"{chi2_amigo:.6f}", f"{chi2_amigo - best:.1e}", "0",
        f"{n_amigo}", f"{cold_amigo:.2f}", f"{1e3 * warm_amigo:.1f}",
    ]  # fmt: skip
    optx_row = [
        f"optimistix LM {COMPANION_TOLERANCE:g}", f"{chi2_optx:.6f}", f"{chi2_optx - best:.1e}",
        f"{shift:.1e}", f"{int(stats['num_steps'])}", f"{cold_optx:.2f}", f"{1e3 * warm_optx:.1f}",
    ]  # fmt: skip
    return amigo_row, optx_row


class _Residuals(eqx.Module):
    """The companion fits' residual function for ``k`` companions (hashable: one compiled
    solver per layout, as amigo's jitted residual-and-Jacobian)."""

    k: int = eqx.field(static=True)
    diameter: float = eqx.field(static=True)

    def __call__(self, y, data):
        return _flat_residual(y, (*data, self.k, self.diameter))


def optimistix_fit_companions(
    dataset, offsets_mas, log10_contrasts, group_scales=None, primary_diameter_mas=0.0,
    max_steps=200, chi2_tolerance=0.0,
):  # fmt: skip
    """:func:`amigo.companions.fit.fit_companions` with optimistix's solver, for timing
    whole detections with it (same start clipping, covariance and result; optimistix
    stops at its own tolerance, ``chi2_tolerance`` is not used)."""
    scales = np.ones(dataset.n_groups) if group_scales is None else np.asarray(group_scales)
    offsets0 = np.asarray(offsets_mas, dtype=float).reshape(-1, 2)
    k = offsets0.shape[0]
    floor = companion_fit.LOG10_CONTRAST_FLOOR
    log10c0 = np.clip(np.asarray(log10_contrasts, float).reshape(k, -1), floor + 1, -1e-3)
    y0 = jnp.asarray(np.concatenate([offsets0.ravel(), log10c0.ravel()]))
    data = (dataset, dataset.scale_vectors(scales))
    function = _Residuals(k, float(primary_diameter_mas))
    x, r, jac, converged, _ = optimistix_levenberg_marquardt(
        function, y0, data, COMPANION_TOLERANCE, max_steps
    )
    x, r, jac = np.asarray(x), np.asarray(r), np.asarray(jac)
    return companion_fit.CompanionFitResult(
        offsets_mas=x[: 2 * k].reshape(k, 2),
        log10_contrasts=np.clip(x[2 * k :].reshape(k, -1), floor, 0.0),
        covariance=np.linalg.pinv(jac.T @ jac, rcond=1e-12, hermitian=True),
        chi2=float(r @ r),
        group_scales=scales,
        converged=bool(converged),
    )


def detection_run(solver: str) -> None:
    """One ``detect`` (no HMC) of the second binary with ``solver``'s companion fits; prints
    a JSON line. Run in a fresh process by :func:`detection`."""
    from amigo.companions.search import SearchSettings, detect

    # Every amigo fit goes through fit_companions_many (fit_companions is one start of
    # it; the search's candidates are many): counted there, one fit per start.
    original = companion_fit.fit_companions_many
    layouts, calls = set(), [0]

    def counted(dataset, starts, *args, **kwargs):
        for offsets_mas, _ in starts:
            layouts.add((dataset.filters, np.shape(offsets_mas)[0]))
        calls[0] += len(starts)
        if solver == "amigo":
            return original(dataset, starts, *args, **kwargs)
        return [optimistix_fit_companions(dataset, o, c, *args, **kwargs) for o, c in starts]

    def counted_one(dataset, offsets_mas, log10_contrasts, *args, **kwargs):
        return counted(dataset, [(offsets_mas, log10_contrasts)], *args, **kwargs)[0]

    companion_fit.fit_companions_many = counted
    if solver != "amigo":
        companion_fit.fit_companions = counted_one
    with tempfile.TemporaryDirectory() as directory:
        dataset, _ = companion_dataset(Path(directory), *BINARIES[1], seed=1)
        result, seconds = wall(lambda: detect(dataset, SearchSettings(rmax_mas=600.0, hmc=False)))
    found = "; ".join(
        f"{c.estimate.sep_mas:.1f} mas {c.estimate.pa_deg:.1f} deg" for c in result.companions
    )
    print(json.dumps(dict(seconds=seconds, fits=calls[0], layouts=len(layouts), found=found)))


def detection() -> list[list[str]]:
    """Whole detections with each solver, as ``amigo detect`` runs them: in a fresh process
    with JAX's persistent compilation cache (every program kept, as amigo's default), first with an
    empty cache, then again with the programs the first run left on disk."""
    rows = []
    for solver in ("amigo", "optimistix"):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(
                os.environ,
                AMIGO_BENCH_XLA_CACHE=cache,
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
            )
            command = [sys.executable, str(Path(__file__)), "--detect-with", solver]
            runs = [
                json.loads(
                    subprocess.run(command, env=env, capture_output=True, text=True, check=True)
                    .stdout.strip()
                    .splitlines()[-1]
                )
                for _ in range(2)
            ]
        rows.append(
            [f"{solver} LM", f"{runs[0]['fits']}", f"{runs[0]['layouts']}",
             f"{runs[0]['seconds']:.1f}", f"{runs[1]['seconds']:.1f}", runs[0]["found"]]
        )  # fmt: skip
    return rows


def companions() -> None:
    print("\n(i) companion fits: amigo.companions.fit.levenberg_marquardt against optimistix")
    jax.config.update("jax_enable_x64", True)
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for case, (separation, pa_deg, mag) in enumerate(BINARIES):
            dataset, truth = companion_dataset(Path(directory), separation, pa_deg, mag, case)
            amigo_row, optx_row = companion_case(dataset, truth)
            n_obs = sum(int(np.size(s)) for s in dataset.scale_vectors(np.ones(dataset.n_groups)))
            rows.append([f"{separation:.0f} mas, {mag:.1f} mag", *amigo_row])
            rows.append([f"  ({n_obs} observables)", *optx_row])
    table(
        "Companion fit (1 companion, 2 filters, 4 parameters, float64); evaluations = residual "
        "+ Jacobian calls (optimistix: steps)",
        ["binary", "solver", "chi2", "- best", "max |dx|/sigma", "evaluations", "cold s",
         "warm ms"],
        rows,
    )  # fmt: skip
    table(
        f"A whole detection of the {BINARIES[1][0]:.0f} mas binary (detect, no HMC, rmax 600 "
        "mas) in a fresh process with the persistent compilation cache: fits = companion fits "
        "(the search's candidates included), layouts = distinct (filters, companions) "
        "compiled; seconds of detect()",
        ["solver", "fits", "layouts", "empty cache s", "second run s",
         "companions found (sep, PA)"],
        detection(),
    )  # fmt: skip
    here, lm = Path(__file__), ROOT / "src" / "amigo" / "companions" / "fit.py"
    # The iteration is one object per problem (_Marquardt), stepped by _marquardt_all, so
    # that the search's candidate fits share their evaluations; levenberg_marquardt wraps
    # them for one problem.
    ours = sum(code_lines(lm, n) for n in ("levenberg_marquardt", "_Marquardt", "_marquardt_all"))
    print(
        "lines of code: amigo companions.fit.levenberg_marquardt (with _Marquardt and "
        f"_marquardt_all) {ours}; its optimistix replacement "
        "(optimistix_levenberg_marquardt, this file) "
        f"{code_lines(here, 'optimistix_levenberg_marquardt')}"
    )


# ------------------------------------------------------------------------ (ii) image fit
class CountedProblem(newton._Problem):
    """The fit's problem, counting what the solver asks for and logging each loss as
    ``(Jacobians so far, seconds since the start, L)``."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.counts = {"loss": 0, "gradient": 0, "normal_equations": 0}
        self.log: list[tuple[int, float, float]] = []
        self.start = time.perf_counter()

    def loss(self, vector):
        self.counts["loss"] += 1
        value = super().loss(vector)
        self.log.append((self.counts["normal_equations"], time.perf_counter() - self.start, value))
        return value

    def gradient(self, vector):
        self.counts["gradient"] += 1
        return super().gradient(vector)

    def normal_equations(self, vector, label):
        self.counts["normal_equations"] += 1
        return super().normal_equations(vector, label)


def image_fit(n_zernike: int):
    """A one-exposure calibrator fit of F480M with ``n_zernike`` Zernikes per hole."""
    from amigo.fitting.filter_fit import FilterFit, FitExposure
    from amigo.likelihood.pixels import ImageData
    from amigo.model.basis import load_basis
    from amigo.model.detector import LinearDetector
    from amigo.model.image import FilterSetup, Instrument
    from amigo.model.optics import LinearSpectrum, NRMOptics, OpticsConfig
    from amigo.model.visibility import UVGrid

    config = OpticsConfig(n_zernike=n_zernike)
    instrument = Instrument(
        optics=NRMOptics.create(config),
        detector=LinearDetector.create(),
        n_wavelengths=2,
        name=f"benchmark-solvers-{n_zernike}z",
    )
    basis, _ = load_basis(instrument, "F480M", UVGrid(7, 0.9))
    setup = FilterSetup.create("F480M", instrument, basis)
    rng = np.random.default_rng(0)
    truth = NRMOptics.create(config, zernikes_nm=jnp.asarray(rng.normal(0, 3.0, (7, n_zernike))))
    spectrum = LinearSpectrum.from_filter("F480M", instrument.n_wavelengths)
    illuminance = truth.illuminance(spectrum, jnp.asarray([0.01, 0.02]))
    model = np.asarray(instrument.detector(illuminance, 1e7), float)
    sigma = np.sqrt(model.clip(0) + 100.0)
    data = ImageData(
        model + sigma * rng.normal(size=model.shape), sigma, np.ones(model.shape, bool)
    )
    fit = FilterFit(instrument, setup, [FitExposure("cal", "calibrator", "CAL", data)])
    return fit, fit.initial_params()


def residual_function(problem: newton._Problem):
    """Whitened residuals of the packed vector (the model, then the priors), float64, as
    the problem defines its loss: ``L = |r|^2 / 2``."""
    from amigo.model.image import filter_psfs
    from amigo.model.image import float64 as to_float64

    lay, fit = problem.layout, problem.fit
    local = jnp.asarray(problem.locals[0])
    optics_index = jnp.asarray(lay.optics)
    instrument, setup = to_float64((fit.instrument, fit.setup))
    data = (
        instrument,
        setup,
        jnp.asarray(fit.anchor, jnp.float64),
        jnp.asarray(problem.data[0]),
        jnp.asarray(problem.weight[0]),
        jnp.sqrt(jnp.asarray(problem.prior_precision)),
        jnp.asarray(problem.prior_centre),
    )

    def residuals(vector, data):
        instrument, setup, anchor, pixels, weight, root_precision, centre = data
        block = vector[optics_index]
        optics = newton._split_block(block, lay.zernike_shape)
        instrument, setup = newton._at(instrument, setup, optics)
        psfs = filter_psfs(instrument, setup, optics, anchor)
        image = newton._local_image(vector[local], instrument, setup, psfs, anchor)
        return jnp.concatenate(
            [(pixels - image.ravel()) * weight, root_precision * (block - centre)]
        )

    return residuals, data


def first_within(log, best: float, margin: float) -> str:
    """``"Jacobians / seconds"`` at the first logged ``L`` with ``2 L - best <= margin``."""
    for jacobians, seconds, loss in log:
        if 2.0 * loss - best <= margin:
            return f"{jacobians} / {seconds:.1f}"
    return "not reached"


def image(n_zernike: int) -> None:
    print(
        f"\n(ii) image fit: amigo.solvers.levenberg_marquardt.minimise against optimistix "
        f"({n_zernike} Zernikes per hole)"
    )
    fit, params = image_fit(n_zernike)
    layout = newton.Layout.of(params)
    start = layout.pack(params)
    members = np.array([0])
    runs: dict[str, dict] = {}

    # amigo: cold (compilation included), then warm at the default and a tight tolerance.
    jax.clear_caches()
    problem = CountedProblem(fit, params, members)
    cold = wall(lambda: minimise(problem, start.copy(), newton.NewtonConfig(), "cold"))[1]
    for name, config in (
        ("amigo minimise, tol 1 (default)", newton.NewtonConfig()),
        ("amigo minimise, tol 0.01", newton.NewtonConfig(tolerance=0.01)),
    ):
        problem = CountedProblem(fit, params, members)
        solution, seconds = wall(lambda p=problem, c=config: minimise(p, start.copy(), c, "bench"))
        runs[name] = dict(
            vector=solution.vector, jacobians=problem.counts["normal_equations"],
            gradients=problem.counts["gradient"], cold=cold if not runs else None,
            warm=seconds, log=problem.log,
        )  # fmt: skip

    # The costs the chord steps trade: one set of Jacobians against one gradient.
    plain = newton._Problem(fit, params, members)
    unit_costs = []
    for precision in (False, True):
        plain.float64 = precision
        plain.normal_equations(start, "warm-up")
        plain.gradient(start)
        unit_costs.append(
            (wall(lambda: plain.normal_equations(start, "bench"))[1],
             wall(lambda: plain.gradient(start))[1])
        )  # fmt: skip

    # optimistix on the packed vector, float64: raw (capped) and Jacobi-scaled.
    packed = newton._Problem(fit, params, members)
    with jax.enable_x64(True):
        residuals, data = residual_function(packed)
        jacobian_of = jax.jit(jax.jacfwd(residuals))
        start64 = jnp.asarray(start)
        jacobian, jac_seconds = wall(lambda: jacobian_of(start64, data))
        scale = jnp.sqrt(jnp.sum(jacobian**2, axis=0))

        def scaled(y, data):
            return residuals(y / data[-1], data[:-1])

        for name, is_scaled, steps in (
            (f"optimistix LM, raw vector ({RAW_STEPS} steps)", False, RAW_STEPS),
            (f"optimistix LM, Jacobi-scaled, tol {IMAGE_TOLERANCE:g}", True, 200),
        ):
            log: list[tuple[int, float, float]] = []
            clock = [0.0]

            def record(step, loss, log=log, clock=clock, extra=int(is_scaled)):
                log.append((int(step) + extra, time.perf_counter() - clock[0], float(loss)))

            def verbose(record=record, **values):
                jax.debug.callback(
                    record, values["num_steps"][1], values["loss_last_accepted_step"][1]
                )

            solver: optx.LevenbergMarquardt = optx.LevenbergMarquardt(
                rtol=IMAGE_TOLERANCE, atol=IMAGE_TOLERANCE, verbose=verbose
            )
            function, y0, arguments = (
                (scaled, start64 * scale, (*data, scale)) if is_scaled
                else (residuals, start64, data)
            )  # fmt: skip

            @eqx.filter_jit
            def run(y0, arguments, function=function, solver=solver, steps=steps):
                return optx.least_squares(
                    function, solver, y0, arguments, max_steps=steps, throw=False
                )

            jax.clear_caches()
            compiled, compile_seconds = wall(
                lambda run=run, y0=y0, a=arguments: run.lower(y0, a).compile()
            )
            clock[0] = time.perf_counter()
            solution, seconds = wall(lambda c=compiled, y0=y0, a=arguments: c(y0, a))
            n_steps = int(solution.stats["num_steps"]) + int(is_scaled)
            value = solution.value / scale if is_scaled else solution.value
            extra = jac_seconds if is_scaled else 0.0  # the Jacobian that gave the scaling
            runs[name] = dict(
                vector=np.asarray(value), jacobians=n_steps, gradients=0,
                cold=compile_seconds + seconds + extra, warm=seconds + extra,
                log=[(j, t + extra, loss) for j, t, loss in log[1:]],
            )  # fmt: skip

        # Every solution judged by the same float64 residuals: chi2, and the distance to
        # the best one in the metric of the Fisher matrix there (sqrt(dx^T F dx), in which
        # exactly degenerate directions cost nothing).
        chi2_of = jax.jit(lambda v, d: jnp.sum(residuals(v, d) ** 2))
        for run_ in runs.values():
            run_["chi2"] = float(chi2_of(jnp.asarray(run_["vector"]), data))
        best_name = min(runs, key=lambda n: runs[n]["chi2"])
        jac = np.asarray(jacobian_of(jnp.asarray(runs[best_name]["vector"]), data))
    best = runs[best_name]["chi2"]
    fisher = jac.T @ jac
    rows, reach = [], []
    for name, run_ in runs.items():
        dx = run_["vector"] - runs[best_name]["vector"]
        cold_text = "" if run_["cold"] is None else f"{run_['cold']:.0f}"
        rows.append(
            [name, f"{run_['chi2']:.3f}", f"{run_['chi2'] - best:.3f}",
             f"{np.sqrt(max(dx @ fisher @ dx, 0.0)):.2f}",
             f"{run_['jacobians']}", f"{run_['gradients']}", cold_text, f"{run_['warm']:.1f}"]
        )  # fmt: skip
        reach.append(
            [name, first_within(run_["log"], best, 1.0), first_within(run_["log"], best, 0.1)]
        )
    n_pixels = int(np.count_nonzero(packed.weight[0]))
    table(
        f"Image fit ({layout.size} parameters, {n_pixels} pixels + priors; float64 judge): "
        "distance = sqrt(dx^T F dx) to the best solution; Jacobians = full Jacobian "
        "evaluations (optimistix: one per step, plus one for the scaling); cold includes "
        "compilation",
        ["solver", "chi2", "- best", "distance", "Jacobians", "gradients", "cold s", "warm s"],
        rows,
    )  # fmt: skip
    table(
        "Reaching the best chi2 (warm): Jacobians / seconds at the first point within",
        ["solver", "1", "0.1"],
        reach,
    )
    (j32, g32), (j64, g64) = unit_costs
    print(
        f"one set of Jacobians (F, g) / one gradient, warm: float32 {j32:.2f} s / {g32:.2f} s, "
        f"float64 {j64:.2f} s / {g64:.2f} s; jax.jacfwd of the residuals (float64, first call "
        f"with compilation): {jac_seconds:.1f} s"
    )
    solvers = ROOT / "src" / "amigo" / "solvers" / "levenberg_marquardt.py"
    print(
        f"lines of code: amigo solvers/levenberg_marquardt.py {code_lines(solvers)} "
        f"(minimise {code_lines(solvers, 'minimise')}, FisherSolve "
        f"{code_lines(solvers, 'FisherSolve')}, marginal_errors "
        f"{code_lines(solvers, 'marginal_errors')})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-companions", action="store_true")
    parser.add_argument("--skip-image", action="store_true")
    parser.add_argument("--image-zernikes", type=int, default=4)
    parser.add_argument("--detect-with", choices=("amigo", "optimistix"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.detect_with:
        jax.config.update("jax_enable_x64", True)
        detection_run(args.detect_with)
        return
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores; "
        f"JAX {jax.__version__} on {jax.default_backend()}, "
        f"optimistix {metadata.version('optimistix')}"
    )
    if not args.skip_companions:
        companions()
    if not args.skip_image:
        jax.config.update("jax_enable_x64", False)  # amigo's image fits run in float32 first
        image(args.image_zernikes)


if __name__ == "__main__":
    main()
