"""Levenberg-Marquardt (damped Gauss-Newton) steps with the full Fisher matrix of a fit.

The natural-gradient descent of :mod:`amigo.fitting` preconditions with a *block-diagonal*
Fisher matrix. That is cheap per iteration but slow where blocks are strongly coupled:
on a calibrator the wavefront and the latent visibilities are nearly degenerate (the
kernel projection exists because of it), and momentum then circles the shallow valley
for hundreds of iterations. An unconverged fit is not a statistical nuisance but a bias:
starting from ``V = 1``, latent visibilities stopped early are shrunk towards zero and
their scatter is smaller than their Hessian errors say.

Here every exposure's image is differentiated exactly (forward mode) with respect to all
the parameters it depends on, the Fisher matrix ``F = sum_e J_e^T W_e J_e`` and the
gradient ``g = sum_e J_e^T W_e r_e`` (``r = data - model``) are assembled in float64 over
one global parameter vector, and the step solves ``(F_s + mu I) d_s = g_s`` in Jacobi-scaled
coordinates (``F_s = D^-1 F D^-1``, ``D = sqrt(diag F)``). Exact degeneracies (the global
piston, the mean hole tilt against the source positions) are dropped by an eigenvalue
floor; ``mu`` grows when a step does not lower the loss and shrinks when it does. The
natural gradient with the *full* Fisher matrix, taken with a unit step, is exactly this
Gauss-Newton step.

Global parameter vector
-----------------------
``[positions (E, 2), log fluxes (E), SED slopes (S), Zernikes (7 x nz), defocus, latent
visibilities (S, m_a + m_p)]``, float64. Science exposures see the wavefront as fixed
(it is fitted on calibrators only), so their Jacobians have no wavefront columns.

Convergence is the Newton decrement ``g^T F^+ g`` (twice the decrease of ``L = chi2/2``
that a full step would give) per exposure, below :attr:`NewtonConfig.tolerance`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo.model import OpticsParams, filter_psfs, illuminance_from_psfs
from amigo.progress import step

if TYPE_CHECKING:
    from amigo.fitting import FilterFit, FitParams

#: Columns differentiated together (memory: each holds the visibility FFTs of one image).
JVP_BATCH = 16
#: Eigenvalues of the Jacobi-scaled Fisher matrix below this fraction of the largest are
#: treated as exact degeneracies: the Jacobians are float32 (~1e-7 relative noise), so
#: smaller eigenvalues are set by rounding, and the gradient's rounding noise along them
#: would dominate both the step and the Newton decrement.
EIGEN_FLOOR = 1e-7


@dataclass(frozen=True)
class NewtonConfig:
    """Settings of :func:`levenberg_marquardt`.

    Attributes
    ----------
    max_iterations
        Jacobian evaluations (each is the cost of one Fisher matrix).
    tolerance
        Converged when the Newton decrement ``g^T F^+ g`` per exposure is below this
        times ``max(1, chi2 / n)`` (``n`` values in the likelihood). It is in units of
        chi2: the Mahalanobis distance squared to the optimum, in all the exposure's few
        hundred parameters together; 1 leaves each parameter within a small fraction of
        its error (0.06 sigma rms for 300 parameters). When the model does not fit to
        the noise (reduced chi2 above 1) the parameter errors grow by that factor, and
        so does the tolerance.
    damping
        Initial Levenberg-Marquardt damping ``mu`` (relative to unit diagonal).
    """

    max_iterations: int = 12
    tolerance: float = 1.0
    damping: float = 1e-3


@dataclass
class NewtonResult:
    """Outcome of :func:`levenberg_marquardt` (``loss`` is ``L = chi2 / 2``)."""

    params: FitParams
    converged: bool
    iterations: int
    loss_history: list[float]
    decrement: float
    seconds: float


# ------------------------------------------------------------------------------ layout
@dataclass(frozen=True)
class Layout:
    """Positions of the parameter groups in the global vector (see module notes)."""

    n_exposures: int
    n_targets: int
    zernike_shape: tuple[int, int]
    n_latent: int

    @property
    def n_zernike(self) -> int:
        return self.zernike_shape[0] * self.zernike_shape[1]

    @property
    def optics(self) -> np.ndarray:
        start = 3 * self.n_exposures + self.n_targets
        return np.arange(start, start + self.n_zernike + 1)

    @property
    def size(self) -> int:
        return int(self.optics[-1]) + 1 + self.n_targets * self.n_latent

    def local(self, e: int, s: int) -> np.ndarray:
        """Indices of ``[x, y, log_flux, slope, latents]`` of exposure ``e`` (target ``s``)."""
        E = self.n_exposures
        latent0 = int(self.optics[-1]) + 1 + s * self.n_latent
        return np.concatenate(
            [[2 * e, 2 * e + 1, 2 * E + e, 3 * E + s], np.arange(latent0, latent0 + self.n_latent)]
        )

    def pack(self, params: FitParams) -> np.ndarray:
        p = params
        return np.concatenate(
            [
                np.ravel(p.exposures.position_arcsec),
                np.ravel(p.exposures.log_flux),
                np.ravel(p.sources.slope_per_um),
                np.ravel(p.optics.zernikes_nm),
                np.ravel(p.optics.defocus_nm),
                np.ravel(np.concatenate([p.sources.amp, p.sources.phase], axis=1)),
            ]
        ).astype(np.float64)

    def unpack(self, params: FitParams, vector: np.ndarray) -> FitParams:
        E, S = self.n_exposures, self.n_targets
        dtype = params.sources.amp.dtype
        n_amp = params.sources.amp.shape[1]
        o = self.optics
        latent = vector[o[-1] + 1 :].reshape(S, self.n_latent)

        def as_(x):
            return jnp.asarray(x, dtype)

        return eqx.tree_at(
            lambda q: (
                q.exposures.position_arcsec,
                q.exposures.log_flux,
                q.sources.slope_per_um,
                q.optics.zernikes_nm,
                q.optics.defocus_nm,
                q.sources.amp,
                q.sources.phase,
            ),
            params,
            (
                as_(vector[: 2 * E].reshape(E, 2)),
                as_(vector[2 * E : 3 * E]),
                as_(vector[3 * E : 3 * E + S]),
                as_(vector[o[:-1]].reshape(self.zernike_shape)),
                as_(vector[o[-1]]),
                as_(latent[:, :n_amp]),
                as_(latent[:, n_amp:]),
            ),
        )

    @classmethod
    def of(cls, params: FitParams) -> Layout:
        return cls(
            n_exposures=int(params.exposures.log_flux.shape[0]),
            n_targets=int(params.sources.slope_per_um.shape[0]),
            zernike_shape=tuple(params.optics.zernikes_nm.shape),
            n_latent=int(params.sources.amp.shape[1] + params.sources.phase.shape[1]),
        )


# ------------------------------------------------------------------------------ images
#: Scalars before the latent visibilities in an exposure's local vector
#: ``[x, y, log_flux, slope, latents]``.
N_LOCAL_SCALARS = 4


def local_vector(params: FitParams, e: int, s: int) -> Float[Array, " n"]:
    """Local vector ``[x, y, log_flux, slope, amp..., phase...]`` of exposure ``e`` of
    target ``s`` (dtype of ``params``)."""
    return jnp.concatenate(
        [
            params.exposures.position_arcsec[e],
            params.exposures.log_flux[e][None],
            params.sources.slope_per_um[s][None],
            params.sources.amp[s],
            params.sources.phase[s],
        ]
    )


def optics_vector(params: FitParams) -> Float[Array, " n"]:
    """``[Zernikes (flattened), defocus]`` of ``params``."""
    return jnp.concatenate([jnp.ravel(params.optics.zernikes_nm), params.optics.defocus_nm[None]])


def local_illuminance(theta, instrument, setup, psfs, anchor) -> Float[Array, "240 240"]:
    """Unit-flux optical illuminance (:func:`amigo.model.illuminance_from_psfs`) of one
    exposure from its local vector ``[x, y, log_flux, slope, latents]`` (the flux,
    ``theta[2]``, is applied by the detector)."""
    n_amp = setup.basis.n_amp
    latent = theta[N_LOCAL_SCALARS:]
    log_amp, phase = setup.basis.grids(latent[:n_amp], latent[n_amp:])
    return illuminance_from_psfs(
        instrument, setup, psfs, theta[3], theta[:2], log_amp, phase, anchor
    )


def _local_image(theta, instrument, setup, psfs, anchor) -> Float[Array, "80 80"]:
    """Image (DN/s) of one exposure from its local vector (as :func:`image_from_psfs`)."""
    optical = local_illuminance(theta, instrument, setup, psfs, anchor)
    return instrument.detector(optical, jnp.exp(theta[2]))


def _columns(function, x: Array) -> Array:
    """Forward-mode Jacobian of ``function`` at ``x``, (n, *out), in batches of columns."""
    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    return jax.lax.map(lambda t: jax.jvp(function, (x,), (t,))[1], eye, batch_size=JVP_BATCH)


@eqx.filter_jit
def local_jacobian(theta, instrument, setup, psfs, anchor) -> Float[Array, "n 80 80"]:
    """Jacobian of one exposure's image w.r.t. its local vector (wavefront held fixed)."""
    return _columns(lambda t: _local_image(t, instrument, setup, psfs, anchor), theta)


@eqx.filter_jit
def optics_jacobian(wavefront, theta, instrument, setup, anchor) -> Float[Array, "n 80 80"]:
    """Jacobian of one exposure's image w.r.t. ``[Zernikes (flattened), defocus]``."""
    shape = instrument.optics.zernikes_nm.shape

    def image_of(vector):
        optics = OpticsParams(vector[:-1].reshape(shape), vector[-1])
        psfs = filter_psfs(instrument, setup, optics, anchor)
        return _local_image(theta, instrument, setup, psfs, anchor)

    return _columns(image_of, wavefront)


@eqx.filter_jit
def psfs_of(instrument, setup, optics, anchor):
    """:func:`amigo.model.filter_psfs`, compiled."""
    return filter_psfs(instrument, setup, optics, anchor)


@eqx.filter_jit
def _images(thetas, instrument, setup, psfs, anchor) -> Float[Array, "e 80 80"]:
    return jax.vmap(lambda t: _local_image(t, instrument, setup, psfs, anchor))(thetas)


# ------------------------------------------------------------------------------ solver
class _Problem:
    """The fit's data and structure as float64 NumPy, with the model as JAX calls."""

    def __init__(self, fit: FilterFit, params: FitParams) -> None:
        self.fit = fit
        self.layout = Layout.of(params)
        self.data = np.asarray(fit.pixels.data, np.float64).reshape(fit.n_exposures, -1)
        self.weight = np.asarray(fit.pixels.inverse_sigma, np.float64).reshape(fit.n_exposures, -1)
        self.locals = [
            self.layout.local(e, int(fit.source_index[e])) for e in range(fit.n_exposures)
        ]
        self.dtype = params.sources.amp.dtype
        self.n_values = float(np.count_nonzero(self.weight))

    def thetas(self, vector: np.ndarray) -> jax.Array:
        return jnp.asarray(np.stack([vector[i] for i in self.locals]), self.dtype)

    def psfs(self, vector: np.ndarray):
        lay = self.layout
        optics = OpticsParams(
            jnp.asarray(vector[lay.optics[:-1]].reshape(lay.zernike_shape), self.dtype),
            jnp.asarray(vector[lay.optics[-1]], self.dtype),
        )
        return psfs_of(self.fit.instrument, self.fit.setup, optics, self.fit.anchor)

    def residuals(self, vector: np.ndarray, psfs=None) -> np.ndarray:
        """(E, npix) whitened residuals ``(data - model) / sigma`` (0 where masked);
        ``psfs`` are those of ``vector``'s wavefront when the caller has them."""
        fit = self.fit
        psfs = self.psfs(vector) if psfs is None else psfs
        models = _images(self.thetas(vector), fit.instrument, fit.setup, psfs, fit.anchor)
        models = np.asarray(models, np.float64).reshape(fit.n_exposures, -1)
        return (self.data - models) * self.weight

    def loss(self, vector: np.ndarray) -> float:
        r = self.residuals(vector)
        return 0.5 * float(np.sum(r * r))

    def normal_equations(self, vector: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
        """Fisher matrix ``F`` and ``g = -grad L`` at ``vector`` (float64)."""
        fit, lay = self.fit, self.layout
        n = lay.size
        fisher, grad = np.zeros((n, n)), np.zeros(n)
        psfs = self.psfs(vector)
        thetas = self.thetas(vector)
        r = self.residuals(vector, psfs)
        wavefront = jnp.asarray(vector[lay.optics], self.dtype)
        for e in range(fit.n_exposures):
            step(f"{label}: Jacobian of {fit.exposures[e].name}")
            jac = local_jacobian(thetas[e], fit.instrument, fit.setup, psfs, fit.anchor)
            jac = np.asarray(jac, np.float64).reshape(len(self.locals[e]), -1)
            index = self.locals[e]
            if fit.is_calibrator[e]:
                jo = optics_jacobian(wavefront, thetas[e], fit.instrument, fit.setup, fit.anchor)
                jac = np.concatenate([jac, np.asarray(jo, np.float64).reshape(len(lay.optics), -1)])
                index = np.concatenate([index, lay.optics])
            wj = jac * self.weight[e]  # whitened Jacobian
            fisher[np.ix_(index, index)] += wj @ wj.T
            grad[index] += wj @ r[e]
        return fisher, grad


def _solve(fisher: np.ndarray, grad: np.ndarray, damping: float) -> np.ndarray:
    """``(F_s + mu I)^-1 g_s`` in Jacobi-scaled coordinates, degenerate directions dropped."""
    diag = np.diag(fisher)
    root = np.sqrt(np.where(diag > 0, diag, 1.0))
    scaled = fisher / np.outer(root, root)
    evals, evecs = np.linalg.eigh(scaled)
    keep = evals > EIGEN_FLOOR * evals.max()
    inv = np.where(keep, 1.0 / (np.where(keep, evals, 1.0) + damping), 0.0)
    step_scaled = evecs @ (inv * (evecs.T @ (grad / root)))
    return np.where(diag > 0, step_scaled / root, 0.0)


def levenberg_marquardt(
    fit: FilterFit,
    params: FitParams,
    config: NewtonConfig | None = None,
    label: str = "fit",
) -> NewtonResult:
    """Damped Gauss-Newton iterations from ``params`` until the Newton decrement is small.

    Each iteration costs one set of Jacobians (the model differentiated with respect to
    every parameter of every exposure); rejected steps only cost a model evaluation.
    """
    config = NewtonConfig() if config is None else config
    start = time.perf_counter()
    problem = _Problem(fit, params)
    per_exposure = float(fit.n_exposures)
    vector = problem.layout.pack(params)
    loss = problem.loss(vector)
    history = [loss]
    damping = config.damping
    decrement = np.inf
    converged = False
    iteration = 0
    for iteration in range(1, config.max_iterations + 1):
        fisher, grad = problem.normal_equations(vector, label)
        decrement = float(grad @ _solve(fisher, grad, 0.0)) / per_exposure
        step(
            f"{label}: Gauss-Newton {iteration}: chi2 {2 * loss:.2f}, "
            f"Newton decrement {decrement:.3g} per exposure"
        )
        scale = max(1.0, 2.0 * loss / problem.n_values)
        if decrement < config.tolerance * scale:
            converged = True
            break
        for _ in range(12):
            trial = vector + _solve(fisher, grad, damping)
            trial_loss = problem.loss(trial)
            if np.isfinite(trial_loss) and trial_loss < loss:
                vector, loss = trial, trial_loss
                damping = max(damping / 3.0, 1e-9)
                break
            damping *= 4.0
        else:
            step(f"{label}: no damped step lowers the loss; stopping")
            break
        history.append(loss)
    return NewtonResult(
        params=problem.layout.unpack(params, vector),
        converged=converged,
        iterations=iteration,
        loss_history=history,
        decrement=decrement,
        seconds=time.perf_counter() - start,
    )
