"""Fit many exposures of one filter jointly, with parameter sharing and natural gradients.

The paper's section "Model Fitting". One :class:`FilterFit` holds every exposure of one
filter (science targets and calibrators); filters share no parameter, so they are fitted
one after the other.

Parameter sharing
-----------------
===================  ==================================  =================================
group                shared by                           fitted on
===================  ==================================  =================================
``position``         one exposure (optical frame, ")     every exposure
``log_flux``         one exposure                        every exposure
``slope``            one target (in this filter)         every exposure of the target
``amp``, ``phase``   one target: latent visibilities     every exposure of the target
``optics``           the filter: 70 Zernikes + defocus   calibrator exposures only
===================  ==================================  =================================

The wavefront is recovered from calibrators only and is held fixed for science targets
(``stop_gradient`` on the science exposures' path), because it is degenerate with the
science visibilities; the kernel projection (:mod:`amigo.observables.kernel`) removes what the
calibrator cannot pin down.

Optimiser
---------
By default, damped Gauss-Newton (Levenberg-Marquardt) steps with the full Fisher matrix
of every exposure (:mod:`amigo.fitting.newton`): the calibrators first, with the wavefront, then
the science exposures with the wavefront held at the calibrators' optimum; between two
sets of Jacobians, chord steps reuse the Fisher matrix with fresh gradients; the normal
equations that confirm convergence (float32 Jacobians, float64 residuals and sums) give
the latent Hessians. The natural gradient with the full Fisher matrix and a unit step
*is* the Gauss-Newton step.

Optionally (``FitConfig.max_iterations > 0``) a first-order stage runs before it:
natural (Fisher-preconditioned) gradient descent. The gradient of ``L = chi2 / 2`` is
preconditioned by Fisher blocks from forward-mode Jacobians (the full block of the
positions, fluxes, slopes, Zernikes and defocus, and each target's latent block or its
diagonal), then passed to optax's Nesterov momentum with one learning rate. Groups start
in stages (positions -> flux -> aberrations -> spectra -> visibilities). Its convergence
is measured: the change of ``L`` over the last :attr:`FitConfig.window` iterations and
the Newton decrement ``g^T F^-1 g`` must both fall below tolerances. An optional
optimistix BFGS polish follows in Fisher-whitened coordinates.

Uncertainties
-------------
:func:`latent_estimates` returns, per target, the latent visibilities and their
covariance: the inverse of the Hessian of ``-log L`` with respect to them at the
optimum, summed in float64, in its Gauss-Newton form ``sum_e J_e^T W_e J_e`` (the Fisher
information; the dropped term is weighted by residuals and has zero expectation). The
Jacobians are computed exactly by forward-mode differentiation of the model.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from amigo import heap, programs
from amigo.fitting.newton import (
    JITTER_INDEX,
    N_LOCAL_SCALARS,
    Layout,
    NewtonConfig,
    levenberg_marquardt,
    local_jacobian,
    local_vector,
    optics_jacobian,
    optics_vector,
    psfs_of,
    whitened,
)
from amigo.fitting.params import FitParams
from amigo.likelihood.pixels import ImageData, PixelData
from amigo.likelihood.stripes import column_whiteners, decorrelate
from amigo.model.image import (
    ExposureParams,
    FilterSetup,
    Instrument,
    OpticsParams,
    SourceParams,
    filter_psfs,
    image_from_psfs,
    locate,
)
from amigo.model.optics import cast as cast_floats
from amigo.progress import step
from amigo.solvers.levenberg_marquardt import FisherSolve

FIT_ROLES = ("science", "calibrator")


@dataclass(frozen=True)
class FitExposure:
    """One exposure to fit.

    Attributes
    ----------
    name
        File name (for reports).
    role
        ``"science"`` or ``"calibrator"``.
    target
        Target name; exposures with the same target (and filter) share visibilities.
    image
        Its :class:`~amigo.likelihood.pixels.ImageData`.
    """

    name: str
    role: str
    target: str
    image: ImageData

    def __post_init__(self) -> None:
        if self.role not in FIT_ROLES:
            raise ValueError(f"role must be one of {FIT_ROLES}, got {self.role!r}")


@dataclass(frozen=True)
class FitConfig:
    """Settings of the optimiser (defaults suit level-2 AMI images).

    Attributes
    ----------
    max_iterations
        Natural-gradient iterations before the Levenberg-Marquardt finish. 0 (default):
        none; the Levenberg-Marquardt solver with chord steps converges from the
        cross-correlation start in a few Jacobian evaluations, and the natural gradient's
        Fisher blocks would cost as much as one of them.
    learning_rate, momentum
        Step scale on the Fisher-preconditioned gradient, and Nesterov momentum.
    starts
        Iteration at which each group starts moving.
    window
        Iterations over which the loss change is measured.
    loss_tolerance
        Converged when the best ``L`` fell by less than this over the last ``window``
        iterations, per exposure (``L = chi2 / 2``) ...
    decrement_tolerance
        ... and the Newton decrement ``g^T F^-1 g`` is below this, per exposure. Both
        are multiplied by the reduced chi2 when it exceeds 1 (a model that does not fit
        to the noise has proportionally larger parameter errors).
    polish_steps
        Maximum BFGS steps after the gradient descent (0: no polish).
    newton
        Levenberg-Marquardt finish with the full Fisher matrix
        (:class:`amigo.fitting.newton.NewtonConfig`; ``max_iterations=0`` switches it off). Its
        Newton decrement then decides convergence.
    vis_preconditioner
        ``"block"`` (full Fisher block of each target's latent visibilities) or
        ``"diagonal"`` (its diagonal only).
    """

    max_iterations: int = 0
    learning_rate: float = 0.3
    momentum: float = 0.6
    starts: dict[str, int] = field(
        default_factory=lambda: {"position": 0, "log_flux": 3, "optics": 10, "slope": 15, "vis": 20}
    )
    window: int = 10
    loss_tolerance: float = 0.05
    decrement_tolerance: float = 1.0
    polish_steps: int = 0
    vis_preconditioner: str = "block"
    newton: NewtonConfig = field(default_factory=NewtonConfig)


@dataclass
class FilterFitResult:
    """Outcome of :meth:`FilterFit.fit`.

    Attributes
    ----------
    params
        Best parameters (float32).
    converged
        Whether the convergence tests passed.
    iterations
        Iterations run: natural-gradient and polishing steps, then Levenberg-Marquardt.
    loss_history
        ``L = chi2 / 2`` per iteration.
    loss_change
        Fall of ``L`` per exposure: over the Levenberg-Marquardt finish's last iteration,
        or, without the finish, of the best ``L`` over the descent's last window.
    newton_decrement
        ``g^T F^-1 g`` at the end (per exposure).
    seconds
        Wall time of the fit.
    fisher, exact_exposures
        The Fisher matrix of the global parameter vector
        (:class:`amigo.fitting.newton.Layout`) at ``params`` summed over the exposures
        ``exact_exposures``, whose convergence the Levenberg-Marquardt finish confirmed
        with float64 residuals there (``None`` and ``()`` if none):
        :func:`latent_information` reads their latent Hessians from it.
    last_fisher
        The Levenberg-Marquardt finish's last Fisher matrix (float32 or float64, at or
        near ``params``; ``None`` without that finish): where a refit's chord steps start.
    fisher_solves
        The solver's decompositions of the stages' matrices summed in ``fisher``
        (:attr:`amigo.fitting.newton.NewtonResult.solves`): marginal errors read them.
    """

    params: FitParams
    converged: bool
    iterations: int
    loss_history: np.ndarray
    loss_change: float
    newton_decrement: float
    seconds: float
    fisher: np.ndarray | None = None
    exact_exposures: tuple[int, ...] = ()
    last_fisher: np.ndarray | None = None
    fisher_solves: tuple[FisherSolve, ...] = ()


class FilterFit:
    """The joint fit of all exposures of one filter (see module notes).

    Parameters
    ----------
    instrument
        Base model.
    setup
        The filter's :class:`~amigo.model.image.FilterSetup` (with its latent basis).
    exposures
        The exposures; targets are taken from them in order of first appearance.
    """

    def __init__(
        self, instrument: Instrument, setup: FilterSetup, exposures: list[FitExposure]
    ) -> None:
        if not exposures:
            raise ValueError("nothing to fit")
        if setup.basis is None:
            raise ValueError("the filter setup has no latent basis")
        self.instrument = instrument
        self.setup = setup
        self.exposures = list(exposures)
        self.targets: list[str] = list(dict.fromkeys(e.target for e in exposures))
        # The solver's stages (calibrators, then science) own disjoint parameters, and
        # the calibration needs a calibrator target: one target in both roles would be
        # neither (the pipeline keys targets by role and visit, amigo.pipeline).
        mixed = [t for t in self.targets if len({e.role for e in exposures if e.target == t}) > 1]
        if mixed:
            raise ValueError(
                f"target(s) {', '.join(mixed)} have both science and calibrator exposures"
            )
        self.source_index = np.array([self.targets.index(e.target) for e in exposures])
        self.is_calibrator = np.array([e.role == "calibrator" for e in exposures])
        self.pixels = jax.tree.map(
            lambda *x: jnp.stack(x), *[PixelData.from_image(e.image) for e in exposures]
        )
        # Offset (x, y, arcsec) at which every exposure's PSFs are computed before the
        # exposure's own offset from it is applied; set by :meth:`initial_params`.
        self.anchor = jnp.zeros(2, jnp.float32)
        # (E,) the 1/f column stripes' standard deviation (DN/s) and correlation length
        # along a column (rows) marginalised in each exposure's likelihood
        # (amigo.likelihood.stripes): measured by the Newton finish where it takes new
        # Jacobians after its cold start's first (amigo.solvers.levenberg_marquardt,
        # "Noise model"); none until then.
        self.stripe_sigma = np.zeros(len(self.exposures))
        self.stripe_length = np.full(len(self.exposures), np.inf)
        # The whiteners of the last stripes asked for (their values as the key): each
        # stage, Hessian and statistic asks again, and the eigendecompositions took
        # ~0.7 s of a one-filter fit when made anew each time.
        self._whiteners: tuple[bytes, np.ndarray] | None = None

    def with_exposures(self, exposures: list[FitExposure]) -> FilterFit:
        """The same fit on other data of the same exposures (e.g. slopes corrected by the
        detector model), keeping the PSF anchor: parameters of this fit mean the same
        model there."""
        names = [e.name for e in exposures]
        if names != [e.name for e in self.exposures]:
            raise ValueError(f"other exposures: {names}")
        other = FilterFit(self.instrument, self.setup, exposures)
        other.anchor = self.anchor
        other.stripe_sigma = self.stripe_sigma.copy()
        other.stripe_length = self.stripe_length.copy()
        return other

    @property
    def stripe_whiteners(self) -> np.ndarray:
        """(E, 80, 80, 80) float64 whiteners of every exposure's columns for its stripes
        (:func:`amigo.likelihood.stripes.column_whiteners`; the identity: no stripes)."""
        key = self.stripe_sigma.tobytes() + self.stripe_length.tobytes()
        if self._whiteners is None or self._whiteners[0] != key:
            whiteners = column_whiteners(
                np.asarray(self.pixels.inverse_sigma), self.stripe_sigma, self.stripe_length
            )
            self._whiteners = (key, whiteners)
        return self._whiteners[1]

    def exposure_whiteners(self) -> list[np.ndarray | None]:
        """Each exposure's (80, 80, 80) stripe whitener (:attr:`stripe_whiteners`),
        ``None`` where no stripes were measured (nothing to apply)."""
        stack = self.stripe_whiteners
        return [w if tau > 0 else None for w, tau in zip(stack, self.stripe_sigma, strict=True)]

    # ------------------------------------------------------------------ model
    @property
    def n_exposures(self) -> int:
        return len(self.exposures)

    def target_roles(self) -> dict[str, str]:
        """Role of each target (every exposure of a target has its role: __init__)."""
        return {
            t: "calibrator"
            if all(e.role == "calibrator" for e in self.exposures if e.target == t)
            else "science"
            for t in self.targets
        }

    def models(
        self,
        params: FitParams,
        instrument: Instrument | None = None,
        setup: FilterSetup | None = None,
    ) -> Float[Array, "e 80 80"]:
        """(E, 80, 80) model images in DN/s."""
        return _model_images(
            params,
            self.instrument if instrument is None else instrument,
            self.setup if setup is None else setup,
            self.anchor,
            tuple(bool(c) for c in self.is_calibrator),
            tuple(int(i) for i in self.source_index),
        )

    def local_jacobians(
        self,
        params: FitParams,
        e: int,
        instrument: Instrument | None = None,
        setup: FilterSetup | None = None,
        wavefront: bool = False,
    ) -> tuple[Array, Array | None]:
        """Forward-mode Jacobians of exposure ``e``'s image (the columns of
        :mod:`amigo.fitting.newton`).

        Returns the (5 + m, 80, 80) Jacobian with respect to the exposure's local vector
        ``[x, y, log_flux, slope, jitter_mas, latent amp..., latent phase...]`` (wavefront held
        fixed; see :data:`amigo.fitting.newton.N_LOCAL_SCALARS`), and, with ``wavefront=True``,
        the (76, 80, 80) Jacobian with respect to the instrument block ``[Zernikes
        (flattened), defocus, geometry, band taper]``
        (else ``None``). Pass a float64 ``instrument``/``setup``/``params`` (inside
        ``jax.enable_x64``) for float64 Jacobians.
        """
        instrument = self.instrument if instrument is None else instrument
        instrument = instrument.with_geometry(params.optics.geometry)
        setup = self.setup if setup is None else setup
        setup = setup.with_band_taper(params.optics.band_taper_per_um2)
        anchor = self.anchor.astype(setup.wavelengths_m.dtype)
        theta = local_vector(params, e, int(self.source_index[e]))
        psfs = psfs_of(instrument, setup, params.optics, anchor)
        local = local_jacobian(theta, instrument, setup, psfs, anchor)
        if not wavefront:
            return local, None
        optics = optics_jacobian(optics_vector(params), theta, instrument, setup, anchor)
        return local, optics

    def latent_jacobian(
        self,
        params: FitParams,
        e: int,
        instrument: Instrument | None = None,
        setup: FilterSetup | None = None,
    ) -> Float[Array, "m 80 80"]:
        """(m_a + m_p, 80, 80) Jacobian of exposure ``e``'s image w.r.t. its target's
        latent visibilities ``[amp, phase]`` (see :meth:`local_jacobians`)."""
        return self.local_jacobians(params, e, instrument, setup)[0][N_LOCAL_SCALARS:]

    def chi2(
        self,
        params: FitParams,
        instrument: Instrument | None = None,
        setup: FilterSetup | None = None,
        pixels: PixelData | None = None,
    ) -> Float[Array, " e"]:
        """(E,) chi-squared of each exposure.

        The arrays (instrument, setup, pixels) can be passed explicitly so that jitted
        callers trace them as arguments instead of folding them in as constants.
        """
        pixels = self.pixels if pixels is None else pixels
        r = (pixels.data - self.models(params, instrument, setup)) * pixels.inverse_sigma
        if np.any(self.stripe_sigma > 0):  # the stripes' covariance (likelihood.stripes)
            # The fit's own whiteners (NumPy, from its pixels): ``pixels`` may be traced.
            r = decorrelate(r, jnp.asarray(self.stripe_whiteners, r.dtype))
        return jnp.sum(r * r, axis=(-2, -1))

    def loss(
        self,
        params: FitParams,
        instrument: Instrument | None = None,
        setup: FilterSetup | None = None,
        pixels: PixelData | None = None,
    ) -> Float[Array, ""]:
        """``L = sum_e chi2_e / 2`` (the negative log-likelihood up to a constant)."""
        return 0.5 * jnp.sum(self.chi2(params, instrument, setup, pixels))

    # ------------------------------------------------------------------ start
    def initial_params(self) -> FitParams:
        """Point sources at cross-correlation positions with summed fluxes, nominal optics."""
        instrument, setup = self.instrument, self.setup
        optics = OpticsParams.from_instrument(instrument)
        jitter_mas = float(instrument.detector.jitter_arcsec) * 1000.0
        # The nominal PSFs by the program the fit reads anyway, the image by one more
        # (the products within 0.005 sigma of op by op: docs/performance.md).
        anchor = jnp.zeros(2, setup.wavelengths_m.dtype)  # centred: filter_psfs' default
        psfs = psfs_of(instrument, setup, optics, anchor)
        template = np.asarray(_template(instrument, setup, psfs, jnp.asarray(jitter_mas)))
        positions, fluxes = [], []
        for exposure in self.exposures:
            position, flux = locate(
                exposure.image.data, exposure.image.mask, template, instrument.detector
            )
            positions.append(position)
            fluxes.append(max(flux, 1e-30))
        # All exposures share one anchor (the mean position) for the PSF computation.
        self.anchor = jnp.asarray(np.mean(positions, axis=0), jnp.float32)
        basis = setup.basis
        assert basis is not None  # checked by __init__
        n_s = len(self.targets)
        return FitParams(
            exposures=ExposureParams(
                jnp.asarray(np.array(positions), jnp.float32),
                jnp.asarray(np.log(fluxes), jnp.float32),
                jnp.full(len(positions), jitter_mas, jnp.float32),
            ),
            sources=SourceParams(
                jnp.zeros((n_s, basis.n_amp), jnp.float32),
                jnp.zeros((n_s, basis.n_phase), jnp.float32),
                jnp.zeros(n_s, jnp.float32),
            ),
            optics=jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), optics),
        )

    # ------------------------------------------------------------------ Fisher
    def preconditioner(self, params: FitParams, vis_mode: str = "block") -> Preconditioner:
        """Fisher information used to precondition the gradient (see module notes).

        The few "small" parameters (positions, fluxes, slopes, Zernikes, defocus) get
        their full Fisher block from forward-mode Jacobians: it captures their strong
        correlations (the mean of the holes' tilts *is* a position shift), which a
        diagonal would turn into oscillations. The latent visibilities get their exact
        Fisher matrix per target (:meth:`fisher_vis`): inverted as a block
        (``vis_mode="block"``, default: a Gauss-Newton step, the log-visibility model
        being nearly linear) or only its diagonal (``"diagonal"``: slower).
        """
        # Independent pixels, the stripes left out: a preconditioner steers, the loss and
        # the Newton finish decide (both with the stripes).
        w = self.pixels.inverse_sigma**2
        blocks: list[Array | None] = []
        for select in _SMALL:
            if select is _optics and not self.is_calibrator.any():
                blocks.append(None)
                continue
            blocks.append(self._jacobian_columns(params, select))
        columns = [b for b in blocks if b is not None]
        jac = jnp.concatenate(columns, axis=0)  # (n_small, E, 80, 80)
        flat = jac.reshape(jac.shape[0], jac.shape[1], -1)
        wf = w.reshape(w.shape[0], -1)
        flat64 = np.asarray(flat, dtype=np.float64)
        fisher = np.einsum("iep,ep,jep->ij", flat64, np.asarray(wf, np.float64), flat64)
        if not self.is_calibrator.any():  # optics: no information, never moves
            n_opt = _pack_sizes(params)[3]
            fisher = np.pad(fisher, ((0, n_opt), (0, n_opt)))
        vis = self.fisher_vis(params)
        if vis_mode == "diagonal":
            # No step (0) where a latent has no information, as in whitening().
            diagonals = [np.diag(f) for f in vis]
            inverse = np.stack(
                [np.diag(np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)) for d in diagonals]
            )
        elif vis_mode == "block":
            inverse = np.stack([_pinv(f, PINV_RCOND) for f in vis])
        else:
            raise ValueError(f"vis_mode must be 'block' or 'diagonal', got {vis_mode!r}")
        return Preconditioner(
            small=jnp.asarray(fisher, dtype=jnp.float32),
            vis_inverse=jnp.asarray(inverse, dtype=jnp.float32),
            vis_diagonal=jnp.asarray(np.stack([np.diag(f) for f in vis]), dtype=jnp.float32),
            groups=_small_groups(params),
        )

    def _jacobian_columns(self, params: FitParams, select) -> Array:
        """(n, E, 80, 80) model Jacobian w.r.t. the scalars of one parameter group."""
        flat, unflatten = _flatten(select(params))

        @eqx.filter_jit
        def columns(params, flat, tangents, instrument, setup):
            def image_of(vector):
                return self.models(
                    eqx.tree_at(select, params, unflatten(vector)), instrument, setup
                )

            return jax.vmap(lambda t: jax.jvp(image_of, (flat,), (t,))[1])(tangents)

        eye = jnp.eye(flat.shape[0], dtype=flat.dtype)
        chunk = 8
        out = []
        for i in range(0, flat.shape[0], chunk):
            block = eye[i : i + chunk]
            pad = chunk - block.shape[0]
            block = jnp.pad(block, ((0, pad), (0, 0)))
            out.append(columns(params, flat, block, self.instrument, self.setup)[: chunk - pad])
        return jnp.concatenate(out)

    def fisher_vis(self, params: FitParams) -> np.ndarray:
        """(S, m, m) Fisher matrices of the latent visibilities ``[amp, phase]``, per target.

        ``F = sum_e J_e^T W_e J_e`` over the target's exposures, with the exact
        Jacobians of :meth:`latent_jacobian` (float32 images, float64 sums).
        """
        n = params.sources.amp.shape[1] + params.sources.phase.shape[1]
        fisher = np.zeros((len(self.targets), n, n))
        root_w = np.asarray(self.pixels.inverse_sigma, dtype=np.float64)
        whiteners = self.exposure_whiteners()
        for e in range(self.n_exposures):
            jac = np.asarray(self.latent_jacobian(params, e)).reshape(n, -1)
            wj = whitened([jac], root_w[e].ravel(), whiteners[e])
            fisher[self.source_index[e]] += wj @ wj.T
        return fisher

    # ------------------------------------------------------------------ optimise
    def fit(
        self,
        config: FitConfig | None = None,
        params: FitParams | None = None,
        label: str = "fit",
    ) -> FilterFitResult:
        """Fit from ``params`` (default :meth:`initial_params`): natural-gradient
        descent for ``config.max_iterations`` steps (none by default) and polishing
        steps, then the Levenberg-Marquardt finish (:mod:`amigo.fitting.newton`) unless
        ``config.newton.max_iterations`` is 0."""
        config = FitConfig() if config is None else config
        start = time.perf_counter()
        params = self.initial_params() if params is None else params
        precond = None
        if (
            config.max_iterations > 0
            or config.polish_steps > 0
            or config.newton.max_iterations == 0
        ):
            precond = self.preconditioner(params, config.vis_preconditioner)
            step(f"{label}: Fisher information computed ({time.perf_counter() - start:.0f} s)")
        starts = jnp.array([config.starts[g] for g in _GROUP_NAMES])
        momentum = optax.trace(decay=config.momentum, nesterov=True)
        state = momentum.init(params)

        @eqx.filter_jit
        def iterate(
            params: FitParams, state, count, rate, instrument, setup, pixels, precond
        ) -> tuple[FitParams, Any, Array, Array]:
            loss, grad = eqx.filter_value_and_grad(self.loss)(params, instrument, setup, pixels)
            natural = precond.natural(grad, count >= starts)
            decrement = _tree_dot(grad, natural)
            updates, state = momentum.update(natural, state, params)
            updates = jax.tree.map(lambda u: -rate * u, updates)
            return eqx.apply_updates(params, updates), state, loss, decrement

        history, decrements = [], []
        best, best_loss, best_iteration = params, np.inf, 0
        last_start = max(config.starts.values())
        converged = False
        per_exposure = float(self.n_exposures)
        n_pixels = float(np.sum(np.asarray(self.pixels.inverse_sigma) > 0))
        iteration = 0
        rate = config.learning_rate
        for iteration in range(1, config.max_iterations + 1):
            new_params, state, loss_array, decrement = iterate(
                params,
                state,
                jnp.asarray(iteration - 1),
                jnp.asarray(rate, jnp.float32),
                self.instrument,
                self.setup,
                self.pixels,
                precond,
            )
            loss = float(loss_array)
            if not np.isfinite(loss) or loss > best_loss + DIVERGENCE * max(best_loss, 1.0):
                # Diverging: go back to the best point, drop the momentum, halve the step.
                rate *= 0.5
                params, state = best, momentum.init(best)
                step(f"{label}: loss rose at iteration {iteration}; step scale now {rate:.3g}")
                if rate < 1e-3 * config.learning_rate:
                    break
                continue
            history.append(loss)
            decrements.append(float(decrement))
            if loss < best_loss:  # the loss belongs to `params`, before this update
                best, best_loss, best_iteration = params, loss, iteration
            elif iteration - best_iteration > config.window and iteration > last_start:
                # No progress for a whole window (momentum circling a shallow valley,
                # e.g. wavefront against calibrator visibilities): back to the best
                # point with a smaller step.
                rate *= 0.5
                params, state = best, momentum.init(best)
                best_iteration = iteration
                step(
                    f"{label}: no progress since iteration {iteration - config.window}; "
                    f"step scale now {rate:.3g}"
                )
                continue
            params = new_params
            if iteration % 25 == 0:
                step(f"{label}: iteration {iteration}, chi2 {2 * loss:.1f}")
            if iteration > last_start + config.window:
                # Progress of the best loss over the window (a loss that wanders without
                # improving has converged as far as this optimiser can take it).
                change = (min(history[: -config.window]) - best_loss) / per_exposure
                # Tolerances are in units of the reduced chi2: when the model cannot fit
                # the data to the noise (chi2/dof > 1), parameter errors grow by that factor.
                scale = max(1.0, 2.0 * loss / n_pixels)
                if (
                    0 <= change < config.loss_tolerance * scale
                    and decrements[-1] / per_exposure < config.decrement_tolerance * scale
                ):
                    converged = True
                    break
        if config.polish_steps > 0:
            assert precond is not None  # computed above when polish_steps > 0
            best, n_polish = self.polish(best, precond, config.polish_steps)
            iteration += n_polish
        fisher: np.ndarray | None = None
        last_fisher: np.ndarray | None = None
        exact: tuple[int, ...] = ()
        solves: tuple[FisherSolve, ...] = ()
        final_loss: float | Array
        if config.newton.max_iterations > 0:
            # The full-Fisher finish decides convergence (see amigo.fitting.newton).
            newton = levenberg_marquardt(self, best, config.newton, label)
            best, converged, fisher = newton.params, newton.converged, newton.fisher
            last_fisher = newton.last_fisher
            exact, solves = newton.exact_exposures, newton.solves
            iteration += newton.iterations
            # The finish's history (levenberg_marquardt: the calibrators' stage, then all
            # exposures) follows the descent's without its starting point where a descent
            # ran; its last value is the final loss (appended below, not twice).
            history.extend(newton.loss_history[1:] if history else newton.loss_history)
            final_loss = history.pop()
            final_decrement = newton.decrement * per_exposure
            change = newton.loss_change
        else:
            final_loss, final_grad = eqx.filter_jit(eqx.filter_value_and_grad(self.loss))(
                best, self.instrument, self.setup, self.pixels
            )
            all_active = jnp.ones(len(_GROUP_NAMES), bool)
            assert precond is not None  # computed above when newton.max_iterations == 0
            final_decrement = float(_tree_dot(final_grad, precond.natural(final_grad, all_active)))
            window = min(config.window, len(history) - 1)
            change = (
                (min(history[:-window]) - min(history)) / per_exposure if window > 0 else np.inf
            )
        return FilterFitResult(
            params=best,
            converged=converged,
            iterations=iteration,
            loss_history=np.array([*history, float(final_loss)]),
            loss_change=float(change),
            newton_decrement=final_decrement / per_exposure,
            seconds=time.perf_counter() - start,
            fisher=fisher,
            exact_exposures=exact,
            last_fisher=last_fisher,
            fisher_solves=solves,
        )

    def polish(
        self, params: FitParams, precond: Preconditioner, max_steps: int
    ) -> tuple[FitParams, int]:
        """BFGS (optimistix) in Fisher-whitened coordinates (diagonal scaling)."""
        import optimistix as optx

        scale = precond.whitening(params)

        def objective(u, args):
            theta = jax.tree.map(lambda p, s, x: p + s * x, params, scale, u)
            return self.loss(theta, *args)

        u0 = jax.tree.map(jnp.zeros_like, params)
        solution: optx.Solution = optx.minimise(
            objective,
            optx.BFGS(rtol=1e-6, atol=1e-3),
            u0,
            args=(self.instrument, self.setup, self.pixels),
            max_steps=max_steps,
            throw=False,
        )
        polished = jax.tree.map(lambda p, s, x: p + s * x, params, scale, solution.value)
        steps = int(solution.stats["num_steps"])
        if not float(self.loss(polished)) < float(self.loss(params)):
            return params, steps
        return polished, steps


# ------------------------------------------------------------------------------ preconditioner
_GROUP_NAMES = ("position", "log_flux", "slope", "optics", "vis")
#: Relative rise of the loss above its best value that counts as divergence.
DIVERGENCE = 0.5
#: Relative eigenvalue floor of the (unit-diagonal) Fisher block of the small parameters.
PINV_RCOND = 1e-5


def _positions(p: FitParams):
    return p.exposures.position_arcsec


def _fluxes(p: FitParams):
    # The jitter moves with the flux (both are per-exposure scalars of the image's shape).
    return (p.exposures.log_flux, p.exposures.jitter_mas)


def _slopes(p: FitParams):
    return p.sources.slope_per_um


def _optics(p: FitParams):
    return p.optics


#: The "small" parameter groups, in packing order (group index = position in the tuple).
_SMALL = (_positions, _fluxes, _slopes, _optics)


def _pack_sizes(params: FitParams) -> list[int]:
    return [sum(int(np.size(x)) for x in jax.tree.leaves(sel(params))) for sel in _SMALL]


def _small_groups(params: FitParams) -> tuple[int, ...]:
    return tuple(g for g, n in enumerate(_pack_sizes(params)) for _ in range(n))


def _pack(params: FitParams) -> Array:
    return jnp.concatenate([jnp.ravel(x) for sel in _SMALL for x in jax.tree.leaves(sel(params))])


def _unpack(params: FitParams, vector: Array) -> FitParams:
    offset = 0
    for sel in _SMALL:
        flat, unflatten = _flatten(sel(params))
        n = flat.shape[0]
        params = eqx.tree_at(sel, params, unflatten(vector[offset : offset + n]))
        offset += n
    return params


def _pinv(matrix: np.ndarray, rcond: float) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix after Jacobi scaling (see natural())."""
    diag = np.diag(matrix)
    root = np.where(diag > 0, np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    evals, evecs = np.linalg.eigh(matrix / np.outer(root, root))
    keep = evals > rcond * evals.max()
    inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    return (evecs * inv) @ evecs.T / np.outer(root, root)


class Preconditioner(eqx.Module):
    """Inverse Fisher information applied to gradients (block-diagonal approximation).

    Attributes
    ----------
    small
        (n, n) Fisher block of the small parameters (packing order of :data:`_SMALL`).
    vis_inverse
        (S, m, m) inverse Fisher block (or inverse diagonal) of each target's latent
        visibilities ``[amp, phase]``.
    vis_diagonal
        (S, m) Fisher diagonal of the latent visibilities (for whitening).
    groups
        (n,) group index of each small parameter.
    """

    small: Array
    vis_inverse: Array
    vis_diagonal: Array
    groups: tuple[int, ...] = eqx.field(static=True)

    def natural(self, grad: FitParams, active: Array) -> FitParams:
        """``F^-1 g`` restricted to the active groups (``active``: (5,) bool)."""
        g = _pack(grad).astype(self.small.dtype)
        mask = active[jnp.asarray(self.groups)].astype(g.dtype)
        # Jacobi scaling (unit diagonal) so that one relative threshold fits parameters
        # of very different units, then a pseudo-inverse: exact degeneracies (the mean
        # hole tilt plus pistons *is* a position shift; the global piston) and inactive
        # groups get no step. The threshold sits above the float32 noise of the block.
        diag = jnp.diag(self.small)
        root = jnp.where(diag > 0, jnp.sqrt(jnp.where(diag > 0, diag, 1.0)), 1.0)
        scaled = self.small / jnp.outer(root, root) * jnp.outer(mask, mask)
        evals, evecs = jnp.linalg.eigh(scaled)
        keep = evals > PINV_RCOND * jnp.max(evals)
        inv = jnp.where(keep, 1.0 / jnp.where(keep, evals, 1.0), 0.0)
        small = (evecs * inv) @ (evecs.T @ (g * mask / root)) / root * mask
        vis_on = active[_GROUP_NAMES.index("vis")]
        n_amp = grad.sources.amp.shape[1]
        latent = jnp.concatenate([grad.sources.amp, grad.sources.phase], axis=1)
        step = jnp.where(vis_on, jnp.einsum("sij,sj->si", self.vis_inverse, latent), 0.0)
        out = eqx.tree_at(
            lambda p: (p.sources.amp, p.sources.phase), grad, (step[:, :n_amp], step[:, n_amp:])
        )
        return _unpack(out, small.astype(grad.sources.amp.dtype))

    def whitening(self, params: FitParams) -> FitParams:
        """``1 / sqrt(F_ii)`` shaped like ``params`` (0 where there is no information)."""
        diag = jnp.diag(self.small)
        small = jnp.where(diag > 0, 1.0 / jnp.sqrt(jnp.where(diag > 0, diag, 1.0)), 0.0)
        out = _unpack(params, small.astype(params.sources.amp.dtype))
        n_amp = params.sources.amp.shape[1]
        d = self.vis_diagonal
        vis = jnp.where(d > 0, 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0)), 0.0)
        return eqx.tree_at(
            lambda p: (p.sources.amp, p.sources.phase), out, (vis[:, :n_amp], vis[:, n_amp:])
        )


# ------------------------------------------------------------------------------ helpers
def _flatten(tree):
    """Concatenate a pytree's leaves into a vector; return it and the inverse map."""
    leaves, treedef = jax.tree.flatten(tree)
    shapes = [leaf.shape for leaf in leaves]
    sizes = [int(np.prod(s)) for s in shapes]
    flat = jnp.concatenate([jnp.ravel(leaf) for leaf in leaves])

    def unflatten(vector):
        parts, offset = [], 0
        for shape, size in zip(shapes, sizes, strict=True):
            parts.append(jnp.reshape(vector[offset : offset + size], shape))
            offset += size
        return jax.tree.unflatten(treedef, parts)

    return flat, unflatten


def _tree_dot(a, b) -> Array:
    leaves = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return cast(Array, sum(jnp.sum(x * y) for x, y in leaves))  # sum() starts from int 0


# ------------------------------------------------------------------------------ information
#: Names of the nuisance parameters nulled by the kernel projection, in column order.
def nuisance_names(n_zernike_rows: int = 7, n_zernike: int = 10) -> list[str]:
    """``z<hole>_<noll>`` for the Zernikes, then ``log_flux``, ``slope``, ``defocus`` and
    ``jitter_mas``.

    The jitter is a per-exposure nuisance like the flux: a Gaussian blur multiplies the
    visibilities by a Gaussian in baseline, which the latent amplitudes can mimic; the
    kernel nulls it so that the DISCOs do not depend on how the jitter was split between
    the blur and the latents (a faint companion's amplitude signal otherwise leaks into a
    science exposure's fitted jitter).
    """
    names = [f"z{h}_{j + 1}" for h in range(n_zernike_rows) for j in range(n_zernike)]
    return [*names, "log_flux", "slope", "defocus", "jitter_mas"]


@dataclass
class LatentInformation:
    """Fisher information of one filter's latent visibilities at the optimum (float64).

    Attributes
    ----------
    hessian
        (S, m, m) ``sum_e J_e^T W_e J_e`` per target (``J_e``: exposure image w.r.t. the
        target's latent ``[amp, phase]``).
    cross
        (m, n_nuisance) ``sum_e J_e^T W_e J_theta,e`` over calibrator exposures, with
        ``theta`` the nuisances of :func:`nuisance_names`, evaluated at the *instrument*
        state of the calibrators (fitted wavefront, positions, fluxes, slopes) with the
        source a point (latent visibilities zero).
    cal_hessian
        (m, m) ``sum_e J_e^T W_e J_e`` over calibrator exposures at the same point-source
        state (the state at which the kernel is defined).
    seconds
        Time taken.
    nuisances
        The names of ``cross``'s columns (:func:`nuisance_names`).

    Why the point-source state: ``d image / d log_flux`` is the model image itself, and
    its regression onto the latent space (:func:`amigo.observables.kernel.nuisance_regression`)
    contains the calibrator's own fitted latents, noise included. A kernel built at the
    fitted state would null the calibrator's measurement (its kernel phases come out at
    ~6% of their variance in the tests) while its covariance is still counted: the
    calibrated DISCOs' errors would be overestimated. The kernel describes the
    instrument's response, so it is evaluated for a point source.
    """

    hessian: np.ndarray
    cross: np.ndarray
    cal_hessian: np.ndarray
    seconds: float
    nuisances: tuple[str, ...] = ()


def latent_information(
    fit: FilterFit,
    params: FitParams,
    label: str = "fit",
    fisher: np.ndarray | None = None,
    exact_exposures: tuple[int, ...] = (),
) -> LatentInformation:
    """Hessians of ``-log L`` w.r.t. the latent visibilities and the nuisance cross terms.

    The Jacobians (forward mode, exact) are float32 and every sum float64, as in the
    solver (:mod:`amigo.fitting.newton`, "Precision"). Covariances use the Hessians
    at the optimum; the kernel's terms are taken at the calibrators' point-source state
    (see :class:`LatentInformation`). ``fisher``: the Fisher matrix of the global vector
    at ``params`` summed over ``exact_exposures`` (:attr:`FilterFitResult.fisher`): the
    latent blocks of those exposures' targets are read from it, the others computed.
    """
    start = time.perf_counter()
    n = params.sources.amp.shape[1] + params.sources.phase.shape[1]
    names = nuisance_names(*params.optics.zernikes_nm.shape)
    hessian = np.zeros((len(fit.targets), n, n))
    cross = np.zeros((n, len(names)))
    cal_hessian = np.zeros((n, n))
    # Whitened Jacobians J / sigma are written in float64 straight from the float32 ones
    # (one float64 copy per Jacobian, ~60 MB for a real exposure, instead of a copy and
    # a weighted product of it): J^T W J = (J / sigma)^T (J / sigma).
    root_w = np.asarray(fit.pixels.inverse_sigma, dtype=np.float64).reshape(fit.n_exposures, -1)
    whiteners = fit.exposure_whiteners()  # and again for the 1/f stripes (likelihood.stripes)
    # The fit's own float32 instrument and setup: the programs the solver compiled.
    instrument, setup, params32 = fit.instrument, fit.setup, cast_floats(params, jnp.float32)
    point = eqx.tree_at(
        lambda p: (p.sources.amp, p.sources.phase),
        params32,
        (jnp.zeros_like(params32.sources.amp), jnp.zeros_like(params32.sources.phase)),
    )
    source = np.asarray(fit.source_index)
    known = set()  # targets whose every exposure is in `fisher`
    if fisher is not None:
        layout = Layout.of(params)
        for s in range(len(fit.targets)):
            members = np.nonzero(source == s)[0]
            if set(members.tolist()) <= set(exact_exposures):
                latent = layout.local(int(members[0]), s)[N_LOCAL_SCALARS:]
                hessian[s] = fisher[np.ix_(latent, latent)]
                known.add(s)
    for e in range(fit.n_exposures):
        if source[e] not in known:
            step(f"{label}: Hessian of {fit.exposures[e].name} ({n} latent visibilities)")
            heap.release()
            jac = np.asarray(fit.latent_jacobian(params32, e, instrument, setup))
            wj = whitened([jac.reshape(n, -1)], root_w[e], whiteners[e])
            del jac
            hessian[fit.source_index[e]] += wj @ wj.T
            del wj
        if fit.is_calibrator[e]:
            step(f"{label}: kernel Jacobians of {fit.exposures[e].name} (point source)")
            heap.release()
            local, wave = fit.local_jacobians(point, e, instrument, setup, wavefront=True)
            assert wave is not None  # wavefront=True returns the optics block
            # Columns in the order of nuisance_names(): Zernikes, log-flux, slope,
            # defocus, jitter (the instrument block is [Zernikes, defocus, geometry]).
            n_zernike = params.optics.zernikes_nm.size
            zernikes, defocus = wave[:n_zernike], wave[n_zernike : n_zernike + 1]
            jitter = local[JITTER_INDEX : JITTER_INDEX + 1]
            nuis = np.concatenate([zernikes, local[2:4], defocus, jitter])
            nuis = whitened([np.asarray(nuis).reshape(len(names), -1)], root_w[e], whiteners[e])
            wj0 = whitened(
                [np.asarray(local[N_LOCAL_SCALARS:]).reshape(n, -1)], root_w[e], whiteners[e]
            )
            del local, wave
            cross += wj0 @ nuis.T
            cal_hessian += wj0 @ wj0.T
            del wj0
    seconds = time.perf_counter() - start
    return LatentInformation(hessian, cross, cal_hessian, seconds, tuple(names))


# One program: op by op, the template took 0.3 s of each fit's start (docs/performance.md).
@programs.jit
def _template(instrument: Instrument, setup: FilterSetup, psfs: Array, jitter_mas: Array) -> Array:
    """(80, 80) a centred point source of flat spectrum with the ``psfs`` (centred) and a
    jitter of ``jitter_mas`` (:meth:`FilterFit.initial_params` cross-correlates it)."""
    exposure = ExposureParams(jnp.zeros(2), jnp.zeros(()), jitter_mas)
    return image_from_psfs(instrument, setup, psfs, jnp.zeros(()), exposure, None, None)


# Compiled as one program: called outside a jit (the products' model images, residuals)
# the model ran op by op, each operation compiling on its own (minutes on a 2-core CPU).
@programs.jit
def _model_images(
    params: FitParams,
    instrument: Instrument,
    setup: FilterSetup,
    anchor: Array,
    calibrator: tuple[bool, ...],
    source_index: tuple[int, ...],
) -> Float[Array, "e 80 80"]:
    """(E, 80, 80) model images in DN/s (:meth:`FilterFit.models`); ``calibrator`` and
    ``source_index`` (static) give each exposure's role and source."""
    instrument = instrument.with_geometry(params.optics.geometry)
    setup = setup.with_band_taper(params.optics.band_taper_per_um2)
    anchor = anchor.astype(setup.wavelengths_m.dtype)
    # Science exposures see the wavefront as a constant (fitted on calibrators only);
    # the PSFs are computed once per role and shared by the exposures.
    shared = filter_psfs(instrument, setup, params.optics, anchor)
    psfs = {True: shared, False: jax.lax.stop_gradient(shared)}
    basis = setup.basis
    assert basis is not None  # FilterFit refuses a setup without its latent basis

    def images(indices: list[int], psfs_of_role: Array) -> Array:
        # The exposures of one role share their PSFs: one vmapped copy of the model.
        exposures = jax.tree.map(lambda x: x[np.array(indices)], params.exposures)
        picked = np.array([source_index[e] for e in indices])
        sources = jax.tree.map(lambda x: x[picked], params.sources)

        def one(exposure, source):
            log_amp, phase = basis.grids(source.amp, source.phase)
            return image_from_psfs(
                instrument, setup, psfs_of_role, source.slope_per_um, exposure, log_amp,
                phase, anchor,
            )  # fmt: skip

        return jax.vmap(one)(exposures, sources)

    groups = {role: [e for e, c in enumerate(calibrator) if c == role] for role in (True, False)}
    stacked = jnp.concatenate([images(groups[r], psfs[r]) for r in (True, False) if groups[r]])
    return stacked[np.argsort(groups[True] + groups[False])]
