"""Science fits through the base model's ramp and read models (``amigo fit --detector``).

The fitting engine (:mod:`amigo.fitting.filter_fit`, :mod:`amigo.fitting.newton`) models an exposure as an
image ``M(theta)`` in DN/s: optics -> latent visibilities -> linear detector. A calslope
file holds ``m = ngroups - 1`` mean slopes ``y`` per pixel (DN per group) and their
covariance; with linear charge accumulation every slope expects ``t_g M`` (``t_g`` the
group time) and :meth:`amigo.likelihood.pixels.ImageData.from_calslope` reduces the slope
likelihood to an image likelihood exactly.

The base model's detector (:meth:`amigo.model.base.BaseModel.slopes`: charge-migration
network, flat field, intra-pixel response, dark, IPC, non-linearity, gain) predicts
instead ``S(theta) = R(I(theta))`` from the same sub-pixel illuminance ``I``. Write ::

    S(theta) = t_g M(theta) + D(theta),     D = S - t_g M,

``D`` (m, 80, 80) being the detector's departure from linear accumulation: brighter-fatter
charge migration, the flat and IPC, the non-linearity. It is a few per cent of the signal
and changes slowly with ``theta``. :func:`fit_through_detector` alternates

1. ``D_k = D(theta_k)``: one forward pass of the ramp model per exposure, no gradient;
2. ``theta_{k+1}``: the linear-detector fit of the corrected slopes ``y - D_k``
   (Levenberg-Marquardt from ``theta_k``),

until ``D`` stops changing (whitened rms change below a tolerance). At the fixed point the
residuals ``y - D(theta) - t_g M(theta) = y - S(theta)`` are those of the full model, so
``fit_summary.json``'s chi2 and z-scores are the full model's, at the slope level.

What the iteration leaves out is ``D``'s own derivative in the normal equations: the step
uses ``t_g dM/dtheta`` where the full model has ``t_g dM/dtheta + dD/dtheta``, as in a
Gauss-Newton method with an approximate Jacobian. The fixed point then differs from the
full-model optimum by ``F^-1 (dD/dtheta)^T W r`` (``r`` the whitened residuals), whose
size relative to the statistical error is that of ``dD/dtheta`` relative to ``t_g
dM/dtheta``, a few per cent; the latent covariances (from ``dM/dtheta``) carry the same
relative approximation. The network is evaluated, never differentiated, which keeps a
science fit at the cost of a linear-detector fit plus one Gauss-Newton refit per round.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo import programs
from amigo.fitting.filter_fit import FilterFit, FilterFitResult, FitConfig, FitExposure
from amigo.fitting.newton import (
    NewtonConfig,
    levenberg_marquardt,
    local_illuminance,
    local_vector,
    psfs_of,
    signature_amplitudes,
)
from amigo.fitting.params import FitParams
from amigo.io.calslope import CalSlope
from amigo.likelihood.pixels import ImageData
from amigo.model.base import BaseModel
from amigo.model.detector.dark_residual import HALO_FRACTION, pattern_amplitude
from amigo.model.detector.reset import Superbias, with_first_group
from amigo.model.image import FilterSetup, Instrument
from amigo.niriss import GAIN_E_PER_DN
from amigo.progress import step

#: A level-2 image keeps the model's read offsets when their pattern's measured amplitude
#: in it is above this (1 where the image is behind the dark reference they describe).
PATTERN_THRESHOLD = 0.5
#: A level-2 image keeps the base model's detector when the measured amplitude of what
#: it adds to the linear image is above this (1: as the model predicts; 0: absent, as in
#: a simulation without JWST's detector effects).
DETECTOR_THRESHOLD = 0.5
#: ... measured only in images the first fit leaves above this pixel z-score standard
#: deviation: where the model with its detector fits at the noise, the data do not
#: contradict the detector, and the measurement (a set of Jacobians, ~6 s per filter on
#: 2 CPU cores) would change nothing. Real COM 1093 images fit at 0.9-1.3; an independent
#: simulation without detector effects, with the detector imposed, at 1.9-2.3.
DETECTOR_CHECK_ZSCORE = 1.5
#: The network's charge migration is rescaled in a filter's calslope exposures when the
#: amplitude measured in them (:meth:`RampDetector.calibrate_migration`) differs from 1
#: by more than this fraction and by more than ``MIGRATION_MIN_SIGMA`` of its error ...
MIGRATION_MIN_CHANGE = 0.1
MIGRATION_MIN_SIGMA = 3.0
#: ... and is kept within this range (a negative migration is not a detector's). The
#: shipped simulator-trained network moves charge as a boundary-shift effect of
#: 1.4-2.1e-6 pix/e- would; JWST's detector, as the real calibrators taught the level-2
#: network, 3.2-5.5e-6 (docs/detector.md): amplitudes of 2-4 are what real ramps may
#: need (3.5 in F480M for 5e-6), and the upper end leaves them room.
MIGRATION_RANGE = (0.0, 6.0)
#: Stop when the whitened rms change of the correction between rounds is below this.
DEFAULT_TOLERANCE = 0.05
#: Rounds of (correction, refit) at most.
DEFAULT_MAX_ROUNDS = 4
#: Gauss-Newton iterations of each refit: a round's change of the correction is a small
#: fraction of the noise, so a few steps from the last optimum absorb it.
DEFAULT_REFIT_ITERATIONS = 3


@dataclass(frozen=True)
class RampInput:
    """A calslope exposure kept whole, for the full detector.

    Attributes
    ----------
    product
        The file's content; with a superbias, its slopes are the values of
        :func:`amigo.model.detector.reset.with_first_group` (the first group less the superbias,
        then the group differences: ``NGROUPS`` values per pixel).
    group_time_s
        Time between group reads (s), from the headers.
    first_group
        Whether the first group is in the likelihood.
    """

    product: CalSlope
    group_time_s: float
    first_group: bool = False

    @classmethod
    def create(
        cls, product: CalSlope, group_time_s: float, superbias: Superbias | None = None
    ) -> RampInput:
        """The exposure with its first group when ``superbias`` is given."""
        if superbias is None:
            return cls(product, group_time_s)
        return cls(with_first_group(product, superbias), group_time_s, first_group=True)

    @property
    def ngroups(self) -> int:
        return int(self.product.ramp_dn.shape[0])

    @property
    def dark_reference(self) -> str:
        """None: amigo processed the raw ramps itself, no pipeline dark was subtracted."""
        return ""

    def image(self, correction_dn: np.ndarray | None) -> ImageData:
        """The exposure reduced to an image after subtracting ``correction_dn``
        (m, ny, nx) DN per group from its values (``None``: none)."""
        product = self.product
        if correction_dn is not None:
            product = dataclasses.replace(product, slope_dn=product.slope_dn - correction_dn)
        return ImageData.from_calslope(
            product, self.group_time_s, leading=1 if self.first_group else 0
        )

    def correction(self, values_dn: np.ndarray, image_dn_s: np.ndarray) -> np.ndarray:
        """``D = S - t_g M`` (m, ny, nx), DN per group: the detector's values ``S`` (its
        first group, when in the likelihood, then its slopes) less the linear image ``M``
        (DN/s) accumulated over a group."""
        return values_dn - image_dn_s[None] * self.group_time_s

    def sigma(self) -> np.ndarray:
        """(m, ny, nx) standard deviation of each value (DN per group)."""
        return np.sqrt(np.einsum("iiyx->iyx", self.product.slope_cov_dn2))


@dataclass(frozen=True)
class Level2Input:
    """A level-2 exposure (``_cal``/``_calints``/``_rateints``) for the full detector.

    The STScI pipeline fitted each pixel's ramp with its weighted least-squares slope
    (:mod:`amigo.model.detector.pipeline_slope`); the forward model is that estimator applied
    to the base model's ramp, so the image expects ``est(R(theta))`` (DN/s) where the
    linear fit models ``M(theta)``; the correction is ``D = est(R) - M``.

    Attributes
    ----------
    data
        The exposure reduced to an image (:meth:`ImageData.from_exposure`).
    ngroups, nframes
        NGROUPS and NFRAMES of the read-out.
    group_time_s
        TGROUP (s).
    dark_reference
        The dark reference file the pipeline subtracted (``R_DARK``): a base model's
        per-group read offsets apply only behind the file they were measured behind
        (:meth:`~amigo.model.base.BaseModel.dark_residual_for`).
    groups_used
        (ny, nx) the leading groups of each pixel the pipeline fitted, where its
        charge-migration step flagged the later ones
        (:func:`~amigo.model.detector.pipeline_slope.charge_loss_groups`); ``None``: all.
    groups_rule
        How ``groups_used`` was found (the step's threshold and where it comes from:
        :func:`amigo.likelihood.pixels.pipeline_groups`), for the terminal.
    """

    data: ImageData
    ngroups: int
    nframes: int
    group_time_s: float
    dark_reference: str = ""
    groups_used: np.ndarray | None = None
    groups_rule: str = ""

    @property
    def first_group(self) -> bool:
        """False: the pipeline's slope has no first group to add (the model's slopes go
        through its estimator)."""
        return False

    def image(self, correction_dn_s: np.ndarray | None) -> ImageData:
        """The image less ``correction_dn_s`` (ny, nx) DN/s (``None``: as read)."""
        if correction_dn_s is None:
            return self.data
        corrected = np.where(self.data.mask, self.data.data - correction_dn_s, 0.0)
        return dataclasses.replace(self.data, data=corrected)

    def correction(self, slopes_dn: np.ndarray, image_dn_s: np.ndarray) -> np.ndarray:
        """``D = est(R) - M`` (ny, nx), DN/s: the pipeline's slope of the base model's
        ramp (its group differences ``slopes_dn``, (m, ny, nx) DN per group, summed from
        zero: the estimator only sees differences) less the linear image."""
        from amigo.model.detector.pipeline_slope import pipeline_group_slope

        per_group = pipeline_group_slope(
            jnp.asarray(slopes_dn), self.group_time_s, GAIN_E_PER_DN, self.nframes,
            self.groups_used,
        )  # fmt: skip
        return np.asarray(per_group, np.float64) / self.group_time_s - image_dn_s

    def sigma(self) -> np.ndarray:
        """(1, ny, nx) standard deviation of the image (DN/s)."""
        return self.data.error[None]

    def with_variance(self, variance_dn_s2: np.ndarray) -> Level2Input:
        """The same image with ``variance_dn_s2`` (ny, nx), (DN/s)^2, added to its
        pixels' variance: noise its ERR does not state (the dark reference's, see
        :meth:`amigo.model.base.BaseModel.dark_offset_terms`)."""
        error = np.sqrt(self.data.error**2 + np.where(self.data.mask, variance_dn_s2, 0.0))
        return dataclasses.replace(self, data=dataclasses.replace(self.data, error=error))


@programs.jit
def _slopes_and_image(
    base: BaseModel,
    instrument: Instrument,
    setup: FilterSetup,
    psfs: Array,
    anchor: Array,
    theta: Float[Array, " n"],
    electrons_per_dn_s: Array,
    ngroups: int,
    first_group: bool = False,
) -> tuple[Float[Array, "m 80 80"], Float[Array, "80 80"]]:
    """The base model's slopes (DN per group; with ``first_group``, the first group's
    value in front of them) and the fit's linear image (DN/s) of one exposure with local
    vector ``theta = [x, y, log_flux, slope, jitter, latents]``."""
    blurred = local_illuminance(theta, instrument, setup, psfs, anchor)
    unit = instrument.detector.resample(blurred)  # sums to the in-field fraction
    flux = jnp.exp(theta[2])
    # The linear image exactly as the refit models it (IPC included where the detector
    # has it), so that D = S - t_g M and the refit's M are the same M.
    image = instrument.detector.after_jitter(blurred, flux)
    # The ramp model runs in the base model's precision (its network is float32), whatever
    # the precision of the optics (float64 when x64 is on).
    electrons = (unit * (flux * electrons_per_dn_s)).astype(base.ramp.flat.dtype)
    if first_group:
        return base.group_values(electrons, ngroups), image
    return base.slopes(electrons, ngroups), image


class RampDetector:
    """The base model's detector in front of a filter's image fit (see module notes).

    Parameters
    ----------
    base
        Base model whose ramp and read models predict the slopes; with its network, or
        without (``with_linear_detector``: linear charge accumulation, flat, IPC and
        non-linearity kept) for ``--detector linear``.
    inputs
        The exposures by :attr:`FitExposure.name`: :class:`RampInput` (calslope files,
        the correction on the slopes) or :class:`Level2Input` (level-2 images, the
        correction through the pipeline's slope estimator on the image; their variance
        gains what the base model does not know of the dark reference's offsets,
        ``added_sigma_dn_s`` holds its median per image).
    tolerance, max_rounds, refit_iterations
        Convergence of the correction and Gauss-Newton iterations per refit (see
        :func:`fit_through_detector`).
    """

    def __init__(
        self,
        base: BaseModel,
        inputs: dict[str, RampInput | Level2Input],
        tolerance: float = DEFAULT_TOLERANCE,
        max_rounds: int = DEFAULT_MAX_ROUNDS,
        refit_iterations: int = DEFAULT_REFIT_ITERATIONS,
    ) -> None:
        self.base = base
        # Level-2 images that do not show the base model's detector (check_detector)
        # are fitted with the linear image alone, as under --detector linear.
        self.detector_amplitudes: dict[str, tuple[float, float]] = {}
        self.without_detector: set[str] = set()
        # Calslope exposures: the amplitude of the network's charge migration measured in
        # their filter (calibrate_migration), whether it was applied, and the scaled
        # models the corrections then use.
        self.migration_amplitudes: dict[str, tuple[float, float, bool]] = {}
        self._scaled: dict[float, BaseModel] = {}
        # Level-2 images carry the dark reference's noise, which their ERR leaves out: the
        # part of it the base model does not know joins each pixel's variance.
        self.added_sigma_dn_s: dict[str, float] = {}
        self.inputs = dict(inputs)
        self.originals = dict(inputs)
        # What the model's offsets add to each level-2 image (DN/s), for the check that
        # the image has them (check_dark_patterns), and its measured amplitude.
        self.patterns: dict[str, np.ndarray] = {}
        self.pattern_amplitudes: dict[str, tuple[float, float]] = {}
        for name, ramp in inputs.items():
            if isinstance(ramp, Level2Input):
                pattern, variance = base.dark_offset_terms(
                    ramp.dark_reference, ramp.data.data, ramp.ngroups, ramp.group_time_s,
                    ramp.nframes, ramp.groups_used,
                )  # fmt: skip
                if pattern is not None:
                    self.patterns[name] = pattern
                if np.any(variance > 0):
                    self.inputs[name] = ramp.with_variance(variance)
                    used = ramp.data.mask
                    self.added_sigma_dn_s[name] = float(np.median(np.sqrt(variance[used])))
        self.tolerance = tolerance
        self.max_rounds = max_rounds
        self.refit_iterations = refit_iterations

    @property
    def mode(self) -> str:
        """``"full"`` with the charge-migration network, ``"boundary"`` with the physical
        account in its place, ``"linear"`` without."""
        return self.base.detector_mode

    def check_dark_patterns(self, fit: FilterFit, params: FitParams) -> list[str]:
        """Measure, in each level-2 image the model's read offsets apply to, the amplitude
        of their pattern in the halo at ``params`` (:func:`pattern_amplitude`; 1: there as
        the model says, 0: absent); images where it is below :data:`PATTERN_THRESHOLD`
        are fitted from now on as images without a subtracted dark (neither the offsets
        nor their variance: e.g. a simulation whose header names the dark file). Returns
        the names of those images; the amplitudes go to ``pattern_amplitudes``."""
        models = np.asarray(fit.models(params), np.float64)
        dropped = []
        for e, exposure in enumerate(fit.exposures):
            name = exposure.name
            pattern = self.patterns.get(name)
            if pattern is None or name in self.pattern_amplitudes or name in self.without_detector:
                continue
            image = exposure.image
            # The fit's residual holds the data less the model with its offsets: adding
            # the pattern back gives what the data say of it.
            residual = image.data - models[e] + pattern
            halo = image.mask & (models[e] < HALO_FRACTION * models[e][image.mask].max())
            amplitude = pattern_amplitude(residual, pattern, image.error**2, halo)
            self.pattern_amplitudes[name] = amplitude
            if not amplitude[0] > PATTERN_THRESHOLD:
                original = self.originals[name]
                assert isinstance(original, Level2Input)  # only level-2 images have patterns
                self.inputs[name] = dataclasses.replace(original, dark_reference="")
                self.added_sigma_dn_s.pop(name, None)
                dropped.append(name)
        return dropped

    def check_detector(
        self,
        fit: FilterFit,
        params: FitParams,
        label: str = "fit",
        newton: NewtonConfig | None = None,
    ) -> list[str]:
        """Measure, in each level-2 image, the amplitude of what the base model's detector
        adds to the linear image at the fit's optimum (1: there as the model says, 0:
        absent): the amplitude of the correction ``B = D`` (charge migration, IPC and
        intra-pixel response, read offsets) fitted together with the other parameters
        (:func:`signature_amplitudes`, one Gauss-Newton step from the optimum; measured
        at fixed parameters it would stay near 1, the parameters having moved to meet
        ``B``). Images below :data:`DETECTOR_THRESHOLD` are fitted from now on with the
        linear image alone, as ``--detector linear`` fits them (e.g. a simulation without
        JWST's detector effects, on which a model calibrated on the real detector would
        imprint them: pixel z-scores 1.8-2.3 instead of ~1.0 on an independent one).
        Only images whose pixel z-scores have a standard deviation above
        :data:`DETECTOR_CHECK_ZSCORE` are measured. Returns the names of the images
        dropped; the amplitudes go to ``detector_amplitudes``. ``newton``: the settings
        the fit was made with (its priors).
        """
        models = np.asarray(fit.models(params), np.float64)
        todo = [
            isinstance(self.inputs[e.name], Level2Input)
            and e.name not in self.detector_amplitudes
            and float(np.std(e.image.zscores(models[i]))) > DETECTOR_CHECK_ZSCORE
            for i, e in enumerate(fit.exposures)
        ]
        if not any(todo):
            return []
        # The images measured as read, without the correction the fit's data carry; the
        # others exactly as the fit has them (their signature is then zero and they only
        # lend the Fisher matrix their Jacobians).
        linear = fit.with_exposures(
            [
                dataclasses.replace(e, image=self.inputs[e.name].image(None)) if todo[i] else e
                for i, e in enumerate(fit.exposures)
            ]
        )
        amplitudes = signature_amplitudes(fit, linear, params, label, newton)
        dropped = []
        for e, exposure in enumerate(fit.exposures):
            if not todo[e]:
                continue
            self.detector_amplitudes[exposure.name] = amplitudes[e]
            if not amplitudes[e][0] > DETECTOR_THRESHOLD:
                # Neither the model's offsets nor their variance: the image as read.
                self.inputs[exposure.name] = self.originals[exposure.name]
                self.added_sigma_dn_s.pop(exposure.name, None)
                self.without_detector.add(exposure.name)
                dropped.append(exposure.name)
        return dropped

    def base_for(self, name: str) -> BaseModel:
        """The base model exposure ``name``'s correction uses: this detector's, with its
        charge migration rescaled where :meth:`calibrate_migration` applied a scale."""
        amplitude, _, applied = self.migration_amplitudes.get(name, (1.0, 0.0, False))
        if not applied:
            return self.base
        if amplitude not in self._scaled:
            self._scaled[amplitude] = self.base.with_migration_scale(amplitude)
        return self._scaled[amplitude]

    def calibrate_migration(
        self,
        fit: FilterFit,
        params: FitParams,
        with_network: list[np.ndarray],
        label: str = "fit",
        newton: NewtonConfig | None = None,
    ) -> tuple[float, float, bool] | None:
        """Measure, in a filter's calslope exposures at the fit's optimum ``params``, the
        amplitude ``a`` of the network's charge migration (1: as the network predicts,
        0: none), and apply it where the data want another one. ``with_network``: the
        corrections at ``params`` as :meth:`corrections` gives them (the caller's next
        round starts from them); ``newton``: the settings the fit was made with.

        The signature is ``B = D1 - D0``, the correction with the network less the
        correction without it (flat, IPC, non-linearity and dark in both), both at
        ``params``; :func:`signature_amplitudes` fits its amplitude in each exposure
        together with every other parameter (what the visibilities, the jitter and the
        wavefront absorb of a fixed blur is not counted as migration), and the filter's
        amplitude is their inverse-variance mean: the migration is the detector's, the
        same in the science and calibrator exposures. Where it differs from 1 by more
        than :data:`MIGRATION_MIN_CHANGE` and :data:`MIGRATION_MIN_SIGMA` errors, the
        corrections from now on use the network scaled by it (clipped to
        :data:`MIGRATION_RANGE`; :meth:`base_for`). Why: a network calibrated on one
        detector (amigo's simulator, or JWST's through the pipeline) stands for a physical
        migration whose strength another detector, or another filter, need not share
        (docs/detector.md, "How strong the networks' charge migration is"). Returns
        ``(a, error, applied)``, or ``None`` where nothing was measured (no network, no
        calslope exposure, or measured before).
        """
        names = [
            e.name
            for e in fit.exposures
            if isinstance(self.inputs[e.name], RampInput)
            and e.name not in self.migration_amplitudes
        ]
        if self.base.linear or not names or len(names) < fit.n_exposures:
            return None
        without = self.corrections(fit, params, self.base.with_linear_detector())
        fit_with = fit.with_exposures(self.corrected(fit.exposures, with_network))
        fit_without = fit.with_exposures(self.corrected(fit.exposures, without))
        amplitudes = signature_amplitudes(
            fit_with, fit_without, params, f"{label}: migration", newton
        )
        values = np.array([a for a, _ in amplitudes])
        weights = np.array([e**-2 if np.isfinite(e) and e > 0 else 0.0 for _, e in amplitudes])
        if not weights.sum() > 0 or not np.all(np.isfinite(values[weights > 0])):
            return None
        amplitude = float(weights @ np.where(weights > 0, values, 0.0) / weights.sum())
        error = float(weights.sum() ** -0.5)
        change = abs(amplitude - 1.0)
        applied = change > MIGRATION_MIN_CHANGE and change > MIGRATION_MIN_SIGMA * error
        if applied:
            amplitude = float(np.clip(amplitude, *MIGRATION_RANGE))
        for name in names:
            self.migration_amplitudes[name] = (amplitude, error, applied)
        return amplitude, error, applied

    def corrections(
        self, fit: FilterFit, params: FitParams, base: BaseModel | None = None
    ) -> list[np.ndarray]:
        """The correction ``D`` of every exposure at ``params``: (m, 80, 80) ``S - t_g M``
        in DN per group for calslope inputs, (80, 80) ``est(R) - M`` in DN/s for level-2
        (zero for the images in ``without_detector``); ``base`` instead of each exposure's
        own model (:meth:`base_for`) where given."""
        setup = fit.setup.with_band_taper(params.optics.band_taper_per_um2)
        instrument = fit.instrument.with_geometry(params.optics.geometry)
        anchor = fit.anchor.astype(setup.wavelengths_m.dtype)
        psfs = psfs_of(instrument, setup, params.optics, anchor)
        gain = self.base.read.gain_e_per_dn
        out = []
        for e, exposure in enumerate(fit.exposures):
            ramp = self.inputs[exposure.name]
            # Electrons per integration for 1 DN/s: reads at t_g, 2 t_g, ... ngroups t_g.
            scale = jnp.asarray(gain * ramp.ngroups * ramp.group_time_s, setup.wavelengths_m.dtype)
            theta = local_vector(params, e, int(fit.source_index[e]))
            if exposure.name in self.without_detector:
                out.append(np.zeros(exposure.image.data.shape))
                continue
            model = self.base_for(exposure.name) if base is None else base
            model = model.dark_residual_for(ramp.dark_reference)
            slopes, image = _slopes_and_image(
                model, instrument, setup, psfs, anchor, theta, scale, ramp.ngroups,
                ramp.first_group,
            )  # fmt: skip
            out.append(
                ramp.correction(np.asarray(slopes, np.float64), np.asarray(image, np.float64))
            )
        return out

    def corrected(
        self, exposures: list[FitExposure], corrections: list[np.ndarray]
    ) -> list[FitExposure]:
        """The exposures with their slopes corrected and reduced to images again."""
        return [
            dataclasses.replace(e, image=self.inputs[e.name].image(d))
            for e, d in zip(exposures, corrections, strict=True)
        ]

    def change(
        self, exposures: list[FitExposure], old: list[np.ndarray], new: list[np.ndarray]
    ) -> float:
        """Whitened rms of ``new - old`` over the values in the likelihood (the largest
        over exposures), in units of each value's own standard deviation (a slope's, or
        a level-2 pixel's)."""
        worst = 0.0
        for exposure, a, b in zip(exposures, old, new, strict=True):
            sigma = self.inputs[exposure.name].sigma()
            delta = np.reshape(b - a, sigma.shape)
            used = np.broadcast_to(exposure.image.mask, sigma.shape)
            with np.errstate(divide="ignore", invalid="ignore"):
                z = delta[used] / sigma[used]
            z = z[np.isfinite(z)]
            worst = max(worst, float(np.sqrt(np.mean(z * z))) if z.size else 0.0)
        return worst


@dataclass(frozen=True)
class DetectorRecord:
    """How the correction converged (``fit_summary.json``'s per-filter record).

    Attributes
    ----------
    mode
        ``"full"`` or ``"linear"``.
    changes
        Whitened rms change of the correction in each round.
    converged
        Whether the last change was below the tolerance.
    seconds
        Wall time of the ramp-model passes and refits.
    """

    mode: str
    changes: tuple[float, ...]
    converged: bool
    seconds: float


def fit_through_detector(
    instrument: Instrument,
    setup: FilterSetup,
    exposures: list[FitExposure],
    config: FitConfig,
    detector: RampDetector,
    label: str = "fit",
) -> tuple[FilterFit, FilterFitResult, DetectorRecord]:
    """Fit a filter's exposures with the base model's detector (see module notes).

    The first correction is taken at the starting point (point sources at their
    cross-correlation positions), the full fit runs on the corrected slopes, and each
    later round recomputes the correction at the current optimum and refits from it by
    Levenberg-Marquardt (``detector.refit_iterations`` steps at most). Returns the fit
    whose data carry the correction at the final parameters (so its residuals are the
    full model's), the result, and the record.
    """
    start = time.perf_counter()
    fit = FilterFit(instrument, setup, exposures)
    corrections = detector.corrections(fit, fit.initial_params())
    step(f"{label}: {detector.mode} detector: correction at the starting point computed")
    fit = fit.with_exposures(detector.corrected(exposures, corrections))
    # Every round is confirmed in float64. (A first round on float32 Jacobians only, whose
    # optimum the next correction moves anyway, saved ~18 s per filter, but the data's
    # correction follows the path of the fits: on the simulated demo the companion landed
    # 0.3 sigma away, both runs converged to a tolerance of 0.01.)
    result = fit.fit(config, label=label)
    # The whole detector first: it compares the fit with the corrections of the inputs
    # as they are, which the dark check may change.
    linear = detector.check_detector(fit, result.params, label, config.newton)
    for name in linear:
        amplitude, error = detector.detector_amplitudes[name]
        step(
            f"{label}: {name}: the base model's detector is not in the image (amplitude "
            f"{amplitude:.2f} +- {error:.2f}): fitted with the linear image alone"
        )
    for name in detector.check_dark_patterns(fit, result.params):
        amplitude, error = detector.pattern_amplitudes[name]
        step(
            f"{label}: {name}: the dark residual's pattern is not in the image (amplitude "
            f"{amplitude:.2f} +- {error:.2f}): fitted without it"
        )
    # The first round's correction, at the optimum: the migration's measurement needs
    # it too, and only a rescaled network makes it stale.
    at_optimum = detector.corrections(fit, result.params)
    migration = detector.calibrate_migration(fit, result.params, at_optimum, label, config.newton)
    rescaled = migration is not None and migration[2]
    first: list[np.ndarray] | None = None if rescaled else at_optimum
    if migration is not None:
        step(
            f"{label}: charge migration {migration[0]:.2f} +- {migration[1]:.2f} of the "
            f"{'network' if detector.mode == 'full' else 'starting strength'}'s"
            f"{': applied' if rescaled else ''}"
        )
    changes: list[float] = []
    refit = dataclasses.replace(
        config.newton,
        max_iterations=min(config.newton.max_iterations, detector.refit_iterations),
    )
    for round_ in range(1, detector.max_rounds + 1):
        new = detector.corrections(fit, result.params) if first is None else first
        first = None
        changes.append(detector.change(fit.exposures, corrections, new))
        corrections = new
        # Same anchor: a fit that recomputed the PSFs elsewhere would not be the model
        # whose parameters `result` holds (it doubled the chi2 of the refits).
        fit = fit.with_exposures(detector.corrected(exposures, corrections))
        step(f"{label}: detector round {round_}: correction changed by {changes[-1]:.3g} sigma")
        last = round_ == detector.max_rounds or config.newton.max_iterations == 0
        settled = changes[-1] < detector.tolerance or last
        confirmed = result.fisher is not None or not config.newton.float64_check
        if settled and confirmed:
            break  # the data now carry the correction at the final parameters
        # The last round's Fisher matrix steers this one's first steps: float64 and exact
        # at its parameters (then convergence may need no new Jacobians at all), or the
        # provisional round's float32 one.
        newton = levenberg_marquardt(
            fit,
            result.params,
            # Images now fitted with the linear image alone, or with a rescaled
            # migration, move far: a whole fit.
            config.newton if round_ == 1 and (linear or rescaled) else refit,
            f"{label} round {round_}",
            result.fisher,
            result.exact_exposures,
            None if result.fisher is not None else result.last_fisher,
        )
        result = FilterFitResult(
            params=newton.params,
            converged=newton.converged,
            iterations=result.iterations + newton.iterations,
            loss_history=np.concatenate([result.loss_history, newton.loss_history]),
            loss_change=newton.loss_change,
            newton_decrement=float(newton.decrement),
            seconds=result.seconds + newton.seconds,
            # The Fisher matrix depends on the parameters and the noise, not on the
            # corrected data: it stays valid for the final round's fit.
            fisher=newton.fisher,
            exact_exposures=newton.exact_exposures,
            last_fisher=newton.last_fisher,
            fisher_solves=newton.solves,
        )
    converged = bool(changes) and changes[-1] < detector.tolerance
    record = DetectorRecord(
        mode=detector.mode,
        changes=tuple(changes),
        converged=converged,
        seconds=time.perf_counter() - start,
    )
    return fit, result, record
