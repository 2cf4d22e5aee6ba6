"""Levenberg-Marquardt (damped Gauss-Newton) steps with the full Fisher matrix of a fit.

The natural-gradient descent of :mod:`amigo.fitting.filter_fit` preconditions with a *block-diagonal*
Fisher matrix. That is cheap per iteration but slow where blocks are strongly coupled:
on a calibrator the wavefront and the latent visibilities are nearly degenerate (the
kernel projection exists because of it), and momentum then circles the shallow valley
for hundreds of iterations. An unconverged fit is not a statistical nuisance but a bias:
starting from ``V = 1``, latent visibilities stopped early are shrunk towards zero and
their scatter is smaller than their Hessian errors say.

Here every exposure's image is differentiated exactly (forward mode) with respect to all
the parameters it depends on, and the Fisher matrix ``F = sum_e J_e^T W_e J_e`` and the
gradient ``g = sum_e J_e^T W_e r_e`` (``r = data - model``) are assembled in float64 over
one global parameter vector: the least-squares problem that
:func:`amigo.solvers.levenberg_marquardt.minimise` solves (damped Gauss-Newton with chord
steps; the natural gradient with the *full* Fisher matrix, taken with a unit step, is
exactly its Gauss-Newton step).

Global parameter vector
-----------------------
``[positions (E, 2), log fluxes (E), SED slopes (S), jitters (E), Zernikes (7 x nz),
defocus, detector geometry (4), band taper, latent visibilities (S, m_a + m_p)]``,
float64. The Zernikes, defocus, geometry and the band-shape correction (the taper of
:class:`~amigo.model.optics.LinearSpectrum`) form the filter's *instrument block*: science exposures
see it as fixed (it is fitted on calibrators only), so their Jacobians have no columns
for it. The geometry has a Gaussian prior centred on the instrument's (the SIAF-derived
nominal, or the base model's) with the widths :data:`GEOMETRY_PRIOR_SIGMA`: wide enough
that a calibrator's data overrule it, narrow enough to keep a fit of few pixels sane; the
band taper one of width :data:`BAND_TAPER_PRIOR_SIGMA` centred on 0.

Convergence is the Newton decrement ``g^T F^+ g`` per exposure, below
:attr:`NewtonConfig.tolerance`.

Cost
----
A set of Jacobians (~1100 forward-mode columns per exposure) costs seconds; a gradient
(one reverse-mode pass over all exposures) a fraction of a second: hence the solver's
chord steps. When they converge, the Fisher matrix at the final point comes back with
the result, and the Hessians of the latent visibilities are read from it instead of
being computed again (:func:`amigo.fitting.filter_fit.latent_information`).

Precision
---------
The model and its residuals ``r`` run in float32 until the solver expects convergence,
then in float64: float32 rounding of a model image (~1e-7 of its peak, ~1e-4 sigma in a
bright pixel, and correlated with the image's structure) sets a floor of about one chi2
unit per exposure on the Newton decrement ``g^T F^+ g`` of a 1000-parameter fit, which
the convergence test reads. The derivatives are linear in what they act on and need no
such care: the Jacobians (forward mode) and the gradient's reverse pass are float32
always, the latter pulling back the residuals of the current precision, and every
product and sum of ``F = J^T W J`` and ``g = J^T W r`` is taken in float64. A relative
error of ~1e-7 in the entries of ``J`` moves ``g`` by ~1e-7 of itself and the Fisher
matrix by ~1e-7 of its norm, far below what a step, the decrement or a covariance can see
(the fits' latent Hessians agree with a float64 evaluation to 6e-5 of their largest
entry or better, as closely as with float64 derivatives, where the solver's last step
sets the difference; tests/test_fit_synthetic.py). Float64 derivatives would compile the
three largest programs a second time (12 s of XLA per configuration on a 2-core CPU,
measured on the tests' small fit) and run at half the speed.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo import heap, programs
from amigo.fitting.params import FitParams
from amigo.likelihood.pixels import PixelData
from amigo.likelihood.stripes import decorrelate_rows, stripes_around_peak
from amigo.model.columns import columns_of
from amigo.model.image import (
    FilterSetup,
    Instrument,
    OpticsParams,
    filter_psf_tangents,
    filter_psfs,
    jittered_illuminance,
)
from amigo.model.image import float64 as _float64
from amigo.model.optics.aperture import HoleWindows, hole_windows
from amigo.progress import step
from amigo.solvers.levenberg_marquardt import FisherSolve, minimise

if TYPE_CHECKING:
    from amigo.model.optics import NRMOptics

#: Standard deviations of the Gaussian prior on ``[rotation_deg, anisotropy, skew_deg,
#: scale]`` around the instrument's geometry: 1 deg, 1 %, 1 deg, 1 % (the real data and
#: an independent simulation move them by < 0.5 deg and < 0.5 %; one calibrator exposure
#: measures them to ~0.01 deg and ~1e-4).
GEOMETRY_PRIOR_SIGMA = (1.0, 0.01, 1.0, 0.01)
#: Size of the detector geometry vector.
N_GEOMETRY = 4
#: Standard deviation of the prior on the band taper (per um^2): 50 lets the band's rms
#: width move by ~10-20 % in the medium-band filters (optics.LinearSpectrum).
BAND_TAPER_PRIOR_SIGMA = 50.0


class JointFit(Protocol):
    """What the problem reads of a joint fit (:class:`amigo.fitting.filter_fit.FilterFit`)."""

    instrument: Instrument
    setup: FilterSetup
    #: The exposures (each with a ``name``), and whether each is a calibrator, (E,).
    exposures: list[Any]
    is_calibrator: np.ndarray
    #: Index of each exposure's target, (E,).
    source_index: np.ndarray
    #: The exposures' pixels, stacked over E.
    pixels: PixelData
    #: Offset (x, y, arcsec) at which the PSFs are computed.
    anchor: Any

    #: (E,) the 1/f column stripes' standard deviation (DN/s) and correlation length
    #: along a column (rows) of each exposure (:mod:`amigo.likelihood.stripes`): the
    #: solver measures them where it takes new Jacobians after the cold start's first,
    #: and writes them here (:meth:`_Problem.refresh`;
    #: :mod:`amigo.solvers.levenberg_marquardt`, "Noise model").
    stripe_sigma: np.ndarray
    stripe_length: np.ndarray

    @property
    def n_exposures(self) -> int: ...

    def exposure_whiteners(self) -> list[np.ndarray | None]:
        """Each exposure's (nx, ny, ny) stripe whitener, ``None`` without stripes."""
        ...


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
    chord_steps
        Most steps taken with the Fisher matrix of the last Jacobians and fresh gradients
        before new Jacobians are computed (0: plain Levenberg-Marquardt).
    float64_check
        Evaluate the model and residuals of the normal equations that are expected to
        confirm convergence in float64, and from then on (and return their Fisher matrix,
        see :class:`NewtonResult`; the Jacobians stay float32, module notes).
    wavefront_prior_nm
        Standard deviation (nm) of an independent Gaussian prior on every Zernike
        coefficient and the defocus, centred on the instrument's own wavefront (the base
        model's calibrated one); ``None``: no prior (the calibrators alone decide).
    geometry_prior_sigma
        Standard deviations of the Gaussian prior on the detector geometry ``[rotation_deg,
        anisotropy, skew_deg, scale]`` around the instrument's (tiny values freeze it).
    jitter_prior_mas
        Standard deviation (mas) of a Gaussian prior holding every exposure's jitter at the
        instrument's; ``None`` (default): free (a tiny value freezes it).
    band_taper_prior
        Standard deviation (per um^2) of the Gaussian prior on the band taper around 0
        (a tiny value freezes it).
    """

    max_iterations: int = 12
    tolerance: float = 1.0
    damping: float = 1e-3
    chord_steps: int = 20
    float64_check: bool = True
    wavefront_prior_nm: float | None = None
    geometry_prior_sigma: tuple[float, float, float, float] = GEOMETRY_PRIOR_SIGMA
    jitter_prior_mas: float | None = None
    band_taper_prior: float = BAND_TAPER_PRIOR_SIGMA


@dataclass
class NewtonResult:
    """Outcome of :func:`levenberg_marquardt` (``loss`` is ``L = chi2 / 2``).

    ``iterations`` counts Gauss-Newton iterations (each with new Jacobians, a given
    matrix, or a confirmation by the float64 gradient), ``chord_steps`` the steps taken
    with a reused Fisher matrix. ``loss`` is ``L`` of all exposures at the end, ``loss_change``
    the fall of ``L`` per exposure over the last iteration of the last stage.

    ``fisher`` is the Fisher matrix ``F`` of the global vector (:class:`Layout`) from the
    last Jacobians of the stages whose convergence float64 residuals confirmed, summed
    over the exposures ``exact_exposures`` of those stages (``None`` if none): evaluated
    within about one sigma per parameter (root mean square) of ``params``, which is one undamped
    Gauss-Newton step from the point of confirmation
    (:func:`amigo.solvers.levenberg_marquardt.minimise`, "Confirmation").
    """

    params: FitParams
    converged: bool
    iterations: int
    loss_history: list[float]
    decrement: float
    seconds: float
    chord_steps: int = 0
    fisher: np.ndarray | None = None
    exact_exposures: tuple[int, ...] = ()
    loss: float = float("nan")
    loss_change: float = float("nan")
    #: The last Fisher matrix of every stage (float32 or float64, at or near ``params``),
    #: summed: what a refit's first chord steps can take (:func:`levenberg_marquardt`).
    last_fisher: np.ndarray | None = None
    #: The solver's decompositions of the stages' matrices in ``fisher``, for
    #: :func:`amigo.solvers.levenberg_marquardt.marginal_errors`.
    solves: tuple[FisherSolve, ...] = ()


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
    def jitters(self) -> np.ndarray:
        start = 3 * self.n_exposures + self.n_targets
        return np.arange(start, start + self.n_exposures)

    @property
    def optics(self) -> np.ndarray:
        """The instrument block ``[Zernikes, defocus, geometry, band taper]``."""
        start = 4 * self.n_exposures + self.n_targets
        return np.arange(start, start + self.n_zernike + 1 + N_GEOMETRY + 1)

    @property
    def wavefront(self) -> np.ndarray:
        """``[Zernikes, defocus]`` (the first part of :attr:`optics`)."""
        return self.optics[: self.n_zernike + 1]

    @property
    def geometry(self) -> np.ndarray:
        """``[rotation_deg, anisotropy, skew_deg, scale]`` (after :attr:`wavefront`)."""
        return self.optics[self.n_zernike + 1 : self.n_zernike + 1 + N_GEOMETRY]

    @property
    def band(self) -> np.ndarray:
        """The band taper (the last entry of :attr:`optics`)."""
        return self.optics[-1:]

    @property
    def size(self) -> int:
        return int(self.optics[-1]) + 1 + self.n_targets * self.n_latent

    def local(self, e: int, s: int) -> np.ndarray:
        """Indices of ``[x, y, log_flux, slope, jitter, latents]`` of exposure ``e``
        (target ``s``)."""
        E = self.n_exposures
        latent0 = int(self.optics[-1]) + 1 + s * self.n_latent
        scalars = [2 * e, 2 * e + 1, 2 * E + e, 3 * E + s, int(self.jitters[e])]
        return np.concatenate([scalars, np.arange(latent0, latent0 + self.n_latent)])

    def pack(self, params: FitParams) -> np.ndarray:
        p = params
        return np.concatenate(
            [
                np.ravel(p.exposures.position_arcsec),
                np.ravel(p.exposures.log_flux),
                np.ravel(p.sources.slope_per_um),
                np.ravel(p.exposures.jitter_mas),
                np.ravel(p.optics.zernikes_nm),
                np.ravel(p.optics.defocus_nm),
                np.ravel(p.optics.geometry),
                np.ravel(p.optics.band_taper_per_um2),
                np.ravel(np.concatenate([p.sources.amp, p.sources.phase], axis=1)),
            ]
        ).astype(np.float64)

    def unpack(self, params: FitParams, vector: np.ndarray) -> FitParams:
        E, S = self.n_exposures, self.n_targets
        dtype = params.sources.amp.dtype
        n_amp = params.sources.amp.shape[1]
        latent = vector[self.optics[-1] + 1 :].reshape(S, self.n_latent)
        wavefront = self.wavefront

        def as_(x):
            return jnp.asarray(x, dtype)

        return eqx.tree_at(
            lambda q: (
                q.exposures.position_arcsec,
                q.exposures.log_flux,
                q.sources.slope_per_um,
                q.exposures.jitter_mas,
                q.optics.zernikes_nm,
                q.optics.defocus_nm,
                q.optics.geometry,
                q.optics.band_taper_per_um2,
                q.sources.amp,
                q.sources.phase,
            ),
            params,
            (
                as_(vector[: 2 * E].reshape(E, 2)),
                as_(vector[2 * E : 3 * E]),
                as_(vector[3 * E : 3 * E + S]),
                as_(vector[self.jitters]),
                as_(vector[wavefront[:-1]].reshape(self.zernike_shape)),
                as_(vector[wavefront[-1]]),
                as_(vector[self.geometry]),
                as_(vector[self.band[0]]),
                as_(latent[:, :n_amp]),
                as_(latent[:, n_amp:]),
            ),
        )

    @classmethod
    def of(cls, params: FitParams) -> Layout:
        return cls(
            n_exposures=int(params.exposures.log_flux.shape[0]),
            n_targets=int(params.sources.slope_per_um.shape[0]),
            zernike_shape=cast(tuple[int, int], tuple(params.optics.zernikes_nm.shape)),
            n_latent=int(params.sources.amp.shape[1] + params.sources.phase.shape[1]),
        )


# ------------------------------------------------------------------------------ images
#: Scalars before the latent visibilities in an exposure's local vector
#: ``[x, y, log_flux, slope, jitter_mas, latents]``.
N_LOCAL_SCALARS = 5
#: Index of the jitter (mas) in the local vector.
JITTER_INDEX = 4


def local_vector(params: FitParams, e: int, s: int) -> Float[Array, " n"]:
    """Local vector ``[x, y, log_flux, slope, jitter_mas, amp..., phase...]`` of exposure
    ``e`` of target ``s`` (dtype of ``params``)."""
    return jnp.concatenate(
        [
            params.exposures.position_arcsec[e],
            params.exposures.log_flux[e][None],
            params.sources.slope_per_um[s][None],
            params.exposures.jitter_mas[e][None],
            params.sources.amp[s],
            params.sources.phase[s],
        ]
    )


def wavefront_vector(optics: OpticsParams | NRMOptics) -> Float[Array, " n"]:
    """``[Zernikes (flattened), defocus]`` of anything holding ``zernikes_nm`` and
    ``defocus_nm`` (an :class:`~amigo.model.image.OpticsParams` or the instrument's optics)."""
    return jnp.concatenate([jnp.ravel(optics.zernikes_nm), jnp.atleast_1d(optics.defocus_nm)])


def optics_vector(params: FitParams) -> Float[Array, " n"]:
    """The instrument block ``[Zernikes (flattened), defocus, geometry, band taper]`` of
    ``params``."""
    o = params.optics
    return jnp.concatenate([wavefront_vector(o), o.geometry, jnp.atleast_1d(o.band_taper_per_um2)])


def _split_block(block: Array, shape: tuple[int, int]) -> OpticsParams:
    """Instrument block -> :class:`OpticsParams`."""
    n = shape[0] * shape[1]
    return OpticsParams(block[:n].reshape(shape), block[n], block[n + 1 : -1], block[-1])


def _at(
    instrument: Instrument, setup: FilterSetup, optics: OpticsParams
) -> tuple[Instrument, FilterSetup]:
    """The instrument and setup with the block's geometry and band taper."""
    return (
        instrument.with_geometry(optics.geometry),
        setup.with_band_taper(optics.band_taper_per_um2),
    )


def local_illuminance(
    theta: Array, instrument: Instrument, setup: FilterSetup, psfs: Array, anchor: Array
) -> Float[Array, "240 240"]:
    """Unit-flux illuminance of one exposure blurred by its jitter
    (:func:`amigo.model.image.jittered_illuminance`) from its local vector ``[x, y,
    log_flux, slope, jitter, latents]`` (the flux, ``theta[2]``, is applied by the
    detector, :meth:`~amigo.model.detector.linear.LinearDetector.after_jitter`)."""
    basis = setup.basis
    assert basis is not None  # a fitted filter's setup has its latent basis
    n_amp = basis.n_amp
    latent = theta[N_LOCAL_SCALARS:]
    log_amp, phase = basis.grids(latent[:n_amp], latent[n_amp:])
    jitter_arcsec = theta[JITTER_INDEX] / 1000.0
    return jittered_illuminance(
        instrument, setup, psfs, theta[3], theta[:2], log_amp, phase, anchor, jitter_arcsec
    )


def _local_image(theta, instrument, setup, psfs, anchor) -> Float[Array, "80 80"]:
    """Image (DN/s) of one exposure from its local vector (as :func:`image_from_psfs`),
    with the detector geometry ``instrument`` holds."""
    blurred = local_illuminance(theta, instrument, setup, psfs, anchor)
    return instrument.detector.after_jitter(blurred, jnp.exp(theta[2]))


@programs.jit
def local_jacobian(
    theta: Array, instrument: Instrument, setup: FilterSetup, psfs: Array, anchor: Array
) -> Float[Array, "n 80 80"]:
    """Jacobian of one exposure's image w.r.t. its local vector (instrument block fixed)."""
    basis = setup.basis
    assert basis is not None  # a fitted filter's setup has its latent basis
    # Scalars, latent amplitudes, latent phases: linearised separately (see columns_of).
    blocks = (N_LOCAL_SCALARS, basis.n_amp)
    return columns_of(lambda t: _local_image(t, instrument, setup, psfs, anchor), theta, blocks)


def optics_jacobian(
    block: Array, theta: Array, instrument: Instrument, setup: FilterSetup, anchor: Array
) -> Float[Array, "n 80 80"]:
    """Jacobian of one exposure's image w.r.t. the instrument block ``[Zernikes
    (flattened), defocus, geometry, band taper]``.

    The Zernike columns go through each hole's window of the pupil
    (:meth:`~amigo.model.optics.NRMOptics.wavefront_psf_tangents`) where the optics
    allows it: the same columns as differentiating the whole model, for less than half
    the cost (docs/performance.md).
    """
    return _optics_jacobian(block, theta, instrument, setup, anchor, _windows(instrument))


def _windows(instrument: Instrument) -> HoleWindows | None:
    """The holes' pupil windows of the optics (host arithmetic on its concrete Zernike
    basis), or ``None`` where the hole-window tangents do not apply: the angular-spectrum
    defocus, a traced mask, or windows too large to save anything."""
    optics = instrument.optics
    c = optics.config
    if c.fresnel and c.defocus_method != "pupil":
        return None
    basis = optics.aperture.zernike_basis(optics.grid, c.n_zernike, c.zernike_radius_factor)
    if isinstance(basis, jax.core.Tracer):
        return None
    windows = hole_windows(np.asarray(basis))
    return windows if windows.size < 0.8 * min(optics.grid.shape) else None


@programs.jit
def _optics_jacobian(
    block: Array,
    theta: Array,
    instrument: Instrument,
    setup: FilterSetup,
    anchor: Array,
    windows: HoleWindows | None,
) -> Float[Array, "n 80 80"]:
    """:func:`optics_jacobian` with the holes' windows (static; ``None``: the whole
    model differentiated)."""
    shape = cast(tuple[int, int], instrument.optics.zernikes_nm.shape)  # (7, n_zernike)
    n_zernike = shape[0] * shape[1]

    def image_of(vector):
        optics = _split_block(vector, shape)
        psfs = filter_psfs(instrument, setup, optics, anchor)
        return _local_image(theta, *_at(instrument, setup, optics), psfs, anchor)

    if windows is None:
        # The wavefront moves the PSFs; the geometry and band taper only the detector and
        # the spectrum: linearised apart, their columns skip the propagation's tangents.
        return columns_of(image_of, block, (n_zernike + 1,))
    optics = _split_block(block, shape)
    psfs, tangents_of = filter_psf_tangents(instrument, setup, optics, anchor, windows)
    # The image is linear in the PSFs: one linearisation carries every PSF tangent.
    at_instrument, at_setup = _at(instrument, setup, optics)
    _, image_tangent = jax.linearize(
        lambda p: _local_image(theta, at_instrument, at_setup, p, anchor), psfs
    )
    columns = jax.lax.map(
        lambda hole: jax.vmap(image_tangent)(tangents_of(hole)), jnp.arange(shape[0])
    )  # (7, n_zernike per hole, 80, 80)
    # The pupil removes the mean piston over the holes (NRMOptics.pupil). A piston common
    # to every hole is a global phase, so this mean is zero up to rounding; it is taken
    # all the same, so that the columns are the model's derivatives by construction.
    columns = columns.at[:, 0].add(-jnp.mean(columns[:, 0], axis=0))
    # Defocus, then the geometry and band taper, as in the whole-model path.
    rest = columns_of(
        lambda tail: image_of(jnp.concatenate([block[:n_zernike], tail])), block[n_zernike:], (1,)
    )
    return jnp.concatenate([columns.reshape(n_zernike, *columns.shape[2:]), rest])


@programs.jit
def psfs_of(
    instrument: Instrument, setup: FilterSetup, optics: OpticsParams, anchor: Array | None
) -> Float[Array, "l 264 264"]:
    """:func:`amigo.model.image.filter_psfs`, compiled."""
    return filter_psfs(instrument, setup, optics, anchor)


@programs.jit
def _images(thetas, instrument, setup, psfs, anchor) -> Float[Array, "e 80 80"]:
    return jax.vmap(lambda t: _local_image(t, instrument, setup, psfs, anchor))(thetas)


@programs.jit
def _gradient(thetas, block, instrument, setup, anchor, pull, wavefront):
    """Gradient of ``L = sum_e |W_e (d_e - m_e)|^2 / 2`` over the exposures whose local
    vectors are ``thetas`` (E, n), w.r.t. those vectors (E, n) and, where ``wavefront`` is
    1, the instrument block ``[Zernikes, defocus, geometry]`` (else 0, not computed), by
    reverse mode, given ``pull`` (E, npix): ``W_e^2 (d_e - m_e)``, the residuals weighted
    twice, from a model of any precision (the reverse pass is linear in it; see the
    module notes, "Precision").

    A stage's exposures are all calibrators (they inform the instrument block) or all
    science exposures (they see it as a constant, as in
    :meth:`amigo.fitting.filter_fit.FilterFit.models`), so one reverse pass of the images
    serves both gradients; ``wavefront`` is a traced 0 or 1, so that both stages share a
    compiled program where they hold as many exposures (one science and one calibrator
    exposure: one program; five calibrator dithers and two science exposures: two).
    """
    shape = instrument.optics.zernikes_nm.shape
    n_wave = shape[0] * shape[1] + 1

    def psfs_of_wavefront(vector):
        optics = _split_block(jnp.concatenate([vector, block[n_wave:]]), shape)
        return filter_psfs(instrument, setup, optics, anchor)

    psfs, pullback = jax.vjp(psfs_of_wavefront, block[:n_wave])

    def images_of(thetas, psfs, rest):
        # ``rest``: the block after the wavefront (geometry, band taper).
        optics = _split_block(jnp.concatenate([block[:n_wave], rest]), shape)
        at_instrument, at_setup = _at(instrument, setup, optics)
        return jax.vmap(lambda t: _local_image(t, at_instrument, at_setup, psfs, anchor))(thetas)

    images, image_pullback = jax.vjp(images_of, thetas, psfs, block[n_wave:])
    # dL/dm_e = -W_e^2 (d_e - m_e)
    g_thetas, g_psfs, g_rest = image_pullback(-pull.reshape(images.shape).astype(images.dtype))
    # The PSFs' reverse pass only where the stage fits the instrument (a branch, not a
    # product with 0: the science stage skips it).
    g_block = jax.lax.cond(
        wavefront > 0,
        lambda: jnp.concatenate([pullback(g_psfs)[0], g_rest]),
        lambda: jnp.zeros(block.shape, block.dtype),
    )
    return g_thetas, g_block


# ------------------------------------------------------------------------------ solver
class _Problem:
    """The fit's data and structure as float64 NumPy, with the model as JAX calls.

    ``members`` are the exposures in this problem (the solver fits the calibrators, then
    the science exposures; see :func:`levenberg_marquardt`). ``float64`` switches the
    model and its residuals to 64-bit (the solver does so near the optimum, where float32
    rounding of the loss hides the last fractions of chi2 that the convergence test asks
    about); the derivatives stay float32 (module notes, "Precision").
    """

    def __init__(
        self,
        fit: JointFit,
        params: FitParams,
        members: np.ndarray,
        wavefront_prior_nm: float | None = None,
        geometry_prior_sigma: tuple[float, ...] = GEOMETRY_PRIOR_SIGMA,
        jitter_prior_mas: float | None = None,
        band_taper_prior: float = BAND_TAPER_PRIOR_SIGMA,
    ) -> None:
        self.fit = fit
        self.layout = Layout.of(params)
        self.members = np.asarray(members, int)
        self.n_groups = len(self.members)
        # The prior acts only where the wavefront is fitted: on the calibrators' stage.
        # A problem's exposures are all calibrators or all science, or every exposure
        # (signature_amplitudes: residuals and Jacobians at the optimum, no gradient).
        calibrators = np.asarray(fit.is_calibrator, bool)[self.members]
        self.fits_wavefront = bool(np.any(calibrators))
        self._one_kind = bool(np.all(calibrators) or not self.fits_wavefront)
        # Gaussian priors on the instrument block (only where it is fitted): the geometry's
        # always, the wavefront's if asked for; zero precision means no prior.
        lay = self.layout
        self.prior_precision = np.zeros(len(lay.optics))
        n_wave = len(lay.wavefront)
        if self.fits_wavefront:
            self.prior_precision[n_wave:-1] = 1.0 / np.square(geometry_prior_sigma)
            self.prior_precision[-1] = 1.0 / float(band_taper_prior) ** 2
            if wavefront_prior_nm is not None:
                self.prior_precision[:n_wave] = 1.0 / float(wavefront_prior_nm) ** 2
        self.prior_centre = np.concatenate(
            [
                np.asarray(wavefront_vector(fit.instrument.optics), np.float64),
                np.asarray(fit.instrument.detector.geometry(), np.float64),
                np.zeros(1),
            ]
        )
        # An optional prior on the members' jitters, centred on the instrument's.
        self.jitter_precision = np.zeros(lay.size)
        if jitter_prior_mas is not None:
            self.jitter_precision[lay.jitters[self.members]] = 1.0 / float(jitter_prior_mas) ** 2
        self.jitter_centre = float(fit.instrument.detector.jitter_arcsec) * 1000.0
        self.data = np.asarray(fit.pixels.data, np.float64).reshape(fit.n_exposures, -1)
        self.weight = np.asarray(fit.pixels.inverse_sigma, np.float64).reshape(fit.n_exposures, -1)
        # The 1/f stripes' whitening (amigo.likelihood.stripes): residuals and Jacobian
        # rows alike, so that every sum below is the stripes' marginal likelihood's.
        self.image_shape = tuple(np.shape(fit.pixels.inverse_sigma)[1:])
        self.stripe_whiteners = fit.exposure_whiteners()
        self.locals = [
            self.layout.local(e, int(fit.source_index[e])) for e in range(fit.n_exposures)
        ]
        self.n_values = float(np.count_nonzero(self.weight[self.members]))
        self.float64 = False
        self._models64: tuple[Instrument, FilterSetup] | None = None
        self._last_residuals: tuple[tuple[bytes, bool], np.ndarray] | None = None
        self._last_models: tuple[tuple[bytes, bool], np.ndarray] | None = None
        self._last_psfs: dict[str, tuple[bytes, Array]] = {}

    @classmethod
    def with_priors(
        cls, fit: JointFit, params: FitParams, members: np.ndarray, config: NewtonConfig
    ) -> _Problem:
        """The problem of ``members`` with the priors of the settings ``config``."""
        return cls(
            fit,
            params,
            members,
            config.wavefront_prior_nm,
            config.geometry_prior_sigma,
            config.jitter_prior_mas,
            config.band_taper_prior,
        )

    def _models(self, float64: bool | None = None):
        if not (self.float64 if float64 is None else float64):
            return self.fit.instrument, self.fit.setup, jnp.float32
        if self._models64 is None:
            self._models64 = _float64((self.fit.instrument, self.fit.setup))
        return (*self._models64, jnp.float64)

    def precision(self) -> AbstractContextManager[Any]:
        """Context in which the model runs in the current precision."""
        return jax.enable_x64(self.float64)

    def _inputs(self, vector: np.ndarray, float64: bool | None = None):
        """The model at ``vector``: the instrument (with the vector's geometry), setup,
        dtype, instrument block, local vectors (E, n) and the PSF anchor, in the current
        precision (``float64``: in that one)."""
        instrument, setup, dtype = self._models(float64)
        lay = self.layout
        block = jnp.asarray(vector[lay.optics], dtype)
        optics = _split_block(block, lay.zernike_shape)
        instrument, setup = _at(instrument, setup, optics)
        thetas = jnp.asarray(np.stack([vector[i] for i in self.locals]), dtype)
        anchor = jnp.asarray(self.fit.anchor, dtype)
        return instrument, setup, dtype, block, thetas, anchor

    def _psfs(self, instrument, setup, block, anchor):
        """The filter's PSFs at the instrument ``block``, the last block's kept per
        precision: the science stage holds the block fixed, and the calibrators' stage
        takes its Jacobians where it has just taken the loss. ``instrument`` and ``setup``
        are those of ``block`` (:meth:`_inputs`), so the block is the key, with the
        precision the PSFs are computed in (a caller's ``jax.enable_x64`` included)."""
        key = np.asarray(block).tobytes()
        context = f"{block.dtype}:{jax.config.read('jax_enable_x64')}"
        kept = self._last_psfs.get(context)
        if kept is not None and kept[0] == key:
            return kept[1]
        optics = _split_block(block, self.layout.zernike_shape)
        psfs = psfs_of(instrument, setup, optics, anchor)
        self._last_psfs[context] = (key, psfs)
        return psfs

    def _images_at(self, vector: np.ndarray) -> np.ndarray:
        """(E, npix) model images (DN/s) at ``vector``, float64 from the current precision,
        of the member exposures, in one batched call; the others' rows hold their data
        (residuals of zero: the problem does not see them, and their images are not
        computed)."""
        models = self.data.copy()
        with self.precision():
            instrument, setup, _, wavefront, thetas, anchor = self._inputs(vector)
            psfs = self._psfs(instrument, setup, wavefront, anchor)
            images = _images(thetas[self.members], instrument, setup, psfs, anchor)
        models[self.members] = np.asarray(images, np.float64).reshape(len(self.members), -1)
        return models

    def _residuals(self, models: np.ndarray) -> np.ndarray:
        """(E, npix) whitened residuals ``(data - model) / sigma`` of every exposure (0
        where masked), whitened again for the exposure's 1/f stripes."""
        return self._whiten_stripes((self.data - models) * self.weight)

    def _whiten_stripes(self, rows: np.ndarray) -> np.ndarray:
        """(E, npix) whitened rows, one per exposure, whitened again for the exposure's
        stripes, in place (:func:`decorrelate_rows`); returned for chaining."""
        for e, whitener in enumerate(self.stripe_whiteners):
            if whitener is not None:
                decorrelate_rows(rows[e : e + 1], whitener)
        return rows

    def refresh(self, vector: np.ndarray) -> bool:
        """Measure the members' 1/f stripes at ``vector`` (:func:`stripes_around_peak` on the
        plain residuals) and whiten for them from here on; ``True`` when the loss changed.

        The solver calls this where it takes new Jacobians, so each Fisher matrix is the
        likelihood's at its point, except the cold start's first (where the model's own
        errors in the halo would inflate the estimate: the first measurement is at the
        next Jacobians, or before a confirmation; :mod:`amigo.solvers.levenberg_marquardt`,
        "Noise model"), the last near the optimum. The values are
        written to the fit (:attr:`JointFit.stripe_sigma`) for what follows (the latent
        Hessians, the next stage, the detector's rounds).
        """
        models = self._models_at(vector)
        changed = False
        for e in self.members:
            inverse_sigma = self.weight[e].reshape(self.image_shape)
            model = models[e].reshape(self.image_shape)
            residual = self.data[e].reshape(self.image_shape) - model
            tau, length = stripes_around_peak(residual, inverse_sigma, model)
            if (tau, length) != (self.fit.stripe_sigma[e], self.fit.stripe_length[e]):
                self.fit.stripe_sigma[e], self.fit.stripe_length[e] = tau, length
                changed = True
        if changed:
            self.stripe_whiteners = self.fit.exposure_whiteners()
            self._last_residuals = None  # whitened for the old stripes
        return changed

    def _prior_offset(self, vector: np.ndarray) -> np.ndarray:
        """Instrument block minus the prior's centre."""
        return vector[self.layout.optics] - self.prior_centre

    def _models_at(self, vector: np.ndarray) -> np.ndarray:
        """:meth:`_images_at` with the last point's kept: the solver asks for the gradient,
        or measures the stripes, where it has just taken the loss."""
        key = (vector.tobytes(), self.float64)
        if self._last_models is None or self._last_models[0] != key:
            self._last_models = (key, self._images_at(vector))
        return self._last_models[1]

    def _residuals_at(self, vector: np.ndarray) -> np.ndarray:
        """:meth:`_residuals` at ``vector`` in the current precision (the last point's kept)."""
        key = (vector.tobytes(), self.float64)
        if self._last_residuals is None or self._last_residuals[0] != key:
            self._last_residuals = (key, self._residuals(self._models_at(vector)))
        return self._last_residuals[1]

    def loss(self, vector: np.ndarray) -> float:
        """``L = chi2 / 2`` of the member exposures at ``vector`` plus the priors'
        ``sum (w - w0)^2 / (2 sigma^2)`` on the instrument block."""
        r = self._residuals_at(vector)[self.members]
        prior = 0.5 * float(np.sum(self.prior_precision * self._prior_offset(vector) ** 2))
        jitter = vector - self.jitter_centre
        prior += 0.5 * float(np.sum(self.jitter_precision * jitter**2))
        return 0.5 * float(np.sum(r * r)) + prior

    def gradient(self, vector: np.ndarray) -> np.ndarray:
        """``g = -grad L`` at ``vector``: one float32 reverse-mode pass of the residuals
        of the current precision (module notes, "Precision")."""
        lay = self.layout
        if not self._one_kind:
            raise ValueError("a gradient needs a problem of calibrators only or science only")
        # J^T C^-1 r: the (stripe-)whitened residuals whitened once more, then / sigma.
        pull = self._whiten_stripes(self._residuals_at(vector).copy()) * self.weight
        instrument, setup, dtype, wavefront, thetas, anchor = self._inputs(vector, float64=False)
        g_thetas, g_wave = _gradient(
            thetas[self.members],
            wavefront,
            instrument,
            setup,
            anchor,
            jnp.asarray(pull[self.members], dtype),
            jnp.asarray(self.fits_wavefront, dtype),
        )
        g_thetas = np.asarray(g_thetas, np.float64)
        g_wave = np.asarray(g_wave, np.float64)
        grad = np.zeros(lay.size)
        for k, e in enumerate(self.members):
            np.add.at(grad, self.locals[e], g_thetas[k])
        grad[lay.optics] += g_wave + self.prior_precision * self._prior_offset(vector)
        grad += self.jitter_precision * (vector - self.jitter_centre)
        return -grad

    def normal_equations(self, vector: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
        """Fisher matrix ``F`` and ``g = -grad L`` at ``vector``: float64 sums of float32
        Jacobians and of the residuals of the current precision (module notes,
        "Precision")."""
        n = self.layout.size
        fisher, grad = np.zeros((n, n)), np.zeros(n)
        r = self._residuals_at(vector)
        for e, index, wj in self.whitened_jacobians(vector, label):
            fisher[np.ix_(index, index)] += wj @ wj.T
            grad[index] += wj @ r[e]
            del wj
        self.add_priors(vector, fisher, grad)
        return fisher, grad

    def whitened_jacobians(
        self, vector: np.ndarray, label: str
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """For each member exposure ``e``: ``(e, index, wj)``, its whitened Jacobian
        (rows: the parameters ``index`` of the global vector, the calibrators' with the
        instrument block; columns: pixels), one float32 Jacobian each."""
        fit, lay = self.fit, self.layout
        instrument, setup, _, wavefront, thetas, anchor = self._inputs(vector, float64=False)
        psfs = self._psfs(instrument, setup, wavefront, anchor)
        for e in self.members:
            residuals = "float64 residuals, " if self.float64 else ""
            step(f"{label}: {residuals}Jacobian of {fit.exposures[e].name}")
            heap.release()  # the peak of a fit's memory is here (amigo.heap)
            parts = [
                np.asarray(local_jacobian(thetas[e], instrument, setup, psfs, anchor)).reshape(
                    len(self.locals[e]), -1
                )
            ]
            index = self.locals[e]
            if fit.is_calibrator[e]:
                jo = optics_jacobian(wavefront, thetas[e], instrument, setup, anchor)
                parts.append(np.asarray(jo).reshape(len(lay.optics), -1))
                index = np.concatenate([index, lay.optics])
            wj = whitened(parts, self.weight[e], self.stripe_whiteners[e])
            del parts
            yield int(e), index, wj

    def add_priors(self, vector: np.ndarray, fisher: np.ndarray, grad: np.ndarray) -> None:
        """Add the priors' terms to a Fisher matrix and a gradient ``-grad L``, in place."""
        lay = self.layout
        fisher[lay.optics, lay.optics] += self.prior_precision
        grad[lay.optics] -= self.prior_precision * self._prior_offset(vector)
        fisher[np.diag_indices(lay.size)] += self.jitter_precision
        grad -= self.jitter_precision * (vector - self.jitter_centre)


def signature_amplitudes(
    fit: JointFit,
    without: JointFit,
    params: FitParams,
    label: str = "fit",
    config: NewtonConfig | None = None,
) -> list[tuple[float, float]]:
    """Per exposure, ``(a, sigma_a)``: how much of a signature in the data the data want.

    ``fit`` and ``without`` are one fit on two versions of the same data: ``y - D1`` and
    ``y - D0`` (e.g. corrected by a detector model with and without a term). Their
    difference ``B = D1 - D0`` is the term's signature; the model family is
    ``y = M(theta) + D0 + a B``. At ``params``, the optimum of ``fit`` (``a = 1``), one
    Gauss-Newton step in ``(theta, a_e)`` for each exposure ``e`` gives ::

        a_e = 1 + (<B, r> - d^T F^-1 g) / (<B, B> - d^T F^-1 d),
        sigma_a = (<B, B> - d^T F^-1 d)^-1/2,

    with ``r`` the exposure's residual, ``<.,.>`` the likelihood's inner product
    (whitened for the noise and the 1/f stripes), ``d = J^T W B`` the pull of the
    signature on the parameters and ``g`` the fit's gradient (zero at an exact optimum).
    The ``d^T F^-1 d`` term is what the parameters can absorb of the signature; without
    it ``a`` would stay near 1 whatever the data (the parameters moved to meet the
    signature).

    ``F``, ``g`` and ``d`` come from one set of whitened Jacobians taken here, at
    ``params`` and with the fit's present stripe whiteners (the calibrators' with the
    wavefront, as in the fit's stages): ``d^T F^-1 d`` is dominated by F's weakest
    directions (the latent knots the data barely see), so a Fisher matrix one step away
    or whitened for other stripes (1 % off) doubled it on a simulated pair. ``F`` is
    scaled to unit diagonal on the parameters it sees and solved with a ridge of 1e-9.
    ``config``: the settings the fit was made with (its priors are part of the
    likelihood whose optimum ``params`` is; default :class:`NewtonConfig`).
    """
    config = NewtonConfig() if config is None else config
    layout = Layout.of(params)
    vector = layout.pack(params)
    members = np.arange(fit.n_exposures)
    with_it = _Problem.with_priors(fit, params, members, config)
    residuals = with_it._residuals_at(vector)
    without_it = _Problem.with_priors(without, params, members, config)
    signatures = without_it._residuals_at(vector) - residuals
    n = layout.size
    fisher, gradient, pulls = np.zeros((n, n)), np.zeros(n), np.zeros((n, fit.n_exposures))
    for e, index, wj in with_it.whitened_jacobians(vector, f"{label}: signature"):
        fisher[np.ix_(index, index)] += wj @ wj.T
        gradient[index] += wj @ residuals[e]
        pulls[index, e] = wj @ signatures[e]
        del wj
    with_it.add_priors(vector, fisher, gradient)
    diagonal = np.diag(fisher)
    used = np.flatnonzero(diagonal > 0)
    scale = diagonal[used] ** -0.5
    scaled = fisher[np.ix_(used, used)] * np.outer(scale, scale)
    scaled[np.diag_indices(len(used))] += 1e-9
    right = np.column_stack([pulls[used], gradient[used]]) * scale[:, None]
    solved = np.linalg.solve(scaled, right) * scale[:, None]
    out = []
    for e in range(fit.n_exposures):
        pull = pulls[used, e]
        information = float(signatures[e] @ signatures[e]) - float(pull @ solved[:, e])
        if not information > 0:
            out.append((float("nan"), float("inf")))
            continue
        # Where ``params`` is not quite the optimum, the step in theta that goes with the
        # one in a: without it, a would carry the rest of the fit's own convergence.
        shift = float(signatures[e] @ residuals[e]) - float(pull @ solved[:, -1])
        out.append((1.0 + shift / information, information**-0.5))
    return out


def whitened(
    blocks: list[np.ndarray], inverse_sigma: np.ndarray, stripe_whitener: np.ndarray | None = None
) -> np.ndarray:
    """(rows, pixels) float64 ``J / sigma`` of a Jacobian given as row blocks, each
    (n_i, pixels) of any float type, stacked in order; with ``stripe_whitener`` (nx, ny,
    ny) of the image, whitened again for its 1/f column stripes
    (:func:`amigo.likelihood.stripes.decorrelate_rows`).

    Written straight into one new array: the same numbers as converting to float64,
    stacking and then weighting, without those intermediate float64 copies (~60 MB each
    for a real exposure).
    """
    out = np.empty((sum(len(block) for block in blocks), blocks[0].shape[1]))
    row = 0
    for block in blocks:
        np.multiply(block, inverse_sigma, out=out[row : row + len(block)])
        row += len(block)
    if stripe_whitener is not None:
        decorrelate_rows(out, stripe_whitener)
    return out


def _stage_indices(layout: Layout, fit: JointFit, members: np.ndarray) -> np.ndarray:
    """Entries of the global vector that the exposures ``members`` inform: their local
    vectors, and the instrument block if one of them is a calibrator."""
    parts = [layout.local(int(e), int(fit.source_index[e])) for e in members]
    if np.any(np.asarray(fit.is_calibrator, bool)[members]):
        parts.append(layout.optics)
    return np.unique(np.concatenate(parts))


def _restricted(fisher: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """``fisher`` with every row and column outside ``indices`` zeroed (one stage's part
    of a matrix summed over the stages: their entries do not overlap)."""
    out = np.zeros_like(fisher)
    out[np.ix_(indices, indices)] = fisher[np.ix_(indices, indices)]
    return out


def levenberg_marquardt(
    fit: JointFit,
    params: FitParams,
    config: NewtonConfig | None = None,
    label: str = "fit",
    fisher: np.ndarray | None = None,
    exact_exposures: tuple[int, ...] = (),
    approximate: np.ndarray | None = None,
) -> NewtonResult:
    """Damped Gauss-Newton iterations from ``params`` until the Newton decrement is small.

    The calibrator exposures are fitted first (with the wavefront), then the science
    exposures with the wavefront held at the calibrators' optimum. This is exactly the
    optimum of the joint fit in which the science exposures see the wavefront as a
    constant (:meth:`amigo.fitting.filter_fit.FilterFit.models`), but, unlike a joint step, each
    stage minimises a proper function: a joint step cannot anticipate how a move of the
    wavefront changes the science images (their Jacobians have no wavefront columns), so
    near the optimum its line search on the total loss refuses steps whose gradient is
    right. Each stage costs one set of Jacobians per iteration and takes up to
    ``config.chord_steps`` chord steps between them (see module notes).

    ``loss_history`` is ``L`` of the calibrators' stage, then ``L`` of all exposures
    during the science stage.

    ``fisher`` and ``exact_exposures``: a previous result's float64 Fisher matrix at (one
    final step from) ``params`` (:attr:`NewtonResult.fisher`) and the exposures it covers. A refit of the
    same model to corrected data (the full detector's rounds) starts every stage whose
    exposures it covers from it instead of from new Jacobians (the Fisher matrix depends
    on the parameters and the noise, not on the data). ``approximate``: else, a previous
    result's :attr:`NewtonResult.last_fisher` (float32 Jacobians, near ``params``), which
    steers every stage's first chord steps before new Jacobians confirm.
    """
    config = NewtonConfig() if config is None else config
    start = time.perf_counter()
    layout = Layout.of(params)
    vector = layout.pack(params)
    calibrator = np.asarray(fit.is_calibrator, bool)
    stages = [
        (np.nonzero(calibrator)[0], f"{label} calibrators"),
        (np.nonzero(~calibrator)[0], f"{label} science"),
    ]
    history: list[float] = []
    converged, iterations, chords, change = True, 0, 0, 0.0
    decrement = 0.0
    # The matrices summed over the stages; made when a stage returns one (each is
    # (size, size) float64, ~40 MB for a real filter's pair of exposures).
    total: np.ndarray | None = None
    last: np.ndarray | None = None
    exact: list[int] = []
    solves: list[FisherSolve] = []
    cal_loss = 0.0
    for members, stage_label in stages:
        if len(members) == 0:
            continue
        problem = _Problem.with_priors(fit, params, members, config)
        # The stage's part of a given matrix is passed without a name here, so that the
        # solver can free it once it has new Jacobians.
        result = minimise(
            problem,
            vector,
            config,
            stage_label,
            *_given_matrix(layout, fit, members, fisher, exact_exposures, approximate),
        )
        if result.last_fisher is not None:
            last = result.last_fisher if last is None else last + result.last_fisher
        vector = result.vector
        converged &= result.converged
        iterations += result.iterations
        chords += result.chord_steps
        history.extend(np.asarray(result.history) + cal_loss)
        cal_loss = history[-1]
        change = result.last_fall / len(members)
        decrement = max(decrement, result.decrement)
        if result.fisher is not None:
            total = result.fisher if total is None else total + result.fisher
            exact.extend(int(e) for e in members)
            assert result.solve is not None  # minimise returns both or neither
            solves.append(result.solve)
        del result
    return NewtonResult(
        params=layout.unpack(params, vector),
        converged=bool(converged),
        iterations=iterations,
        loss_history=history,
        decrement=decrement,
        seconds=time.perf_counter() - start,
        chord_steps=chords,
        fisher=total,
        exact_exposures=tuple(sorted(exact)),
        # The science stage leaves the calibrators' loss unchanged: its history already
        # holds the loss of all exposures.
        loss=float(history[-1]),
        loss_change=float(change),
        last_fisher=np.zeros((layout.size, layout.size)) if last is None else last,
        solves=tuple(solves),
    )


def _given_matrix(
    layout: Layout,
    fit: JointFit,
    members: np.ndarray,
    fisher: np.ndarray | None,
    exact_exposures: tuple[int, ...],
    approximate: np.ndarray | None,
) -> tuple[np.ndarray | None, bool]:
    """The matrix a stage starts from and whether it is exact (:func:`levenberg_marquardt`'s
    ``fisher`` / ``approximate``), restricted to the stage's entries, or ``(None, True)``."""
    indices = _stage_indices(layout, fit, members)
    if fisher is not None and set(members.tolist()) <= set(exact_exposures):
        return _restricted(fisher, indices), True
    if approximate is not None:
        return _restricted(approximate, indices), False
    return None, True
