"""Ramp-level forward model of a calslope exposure, and its slope likelihood.

::

    base model optics (filter)  --  source position, flux
        -> unit illuminance on the detector's 3x grid       BaseModel.illuminance
        -> x flux (electrons per integration)                [visibilities: issue 4]
        -> ramp model (BFE network, flat, intra-pixel)       BaseModel.slopes
        -> read model (dark, IPC, non-linearity, gain)
        -> slopes (ngroups - 1, 80, 80), DN per group
    whitened residuals z = W (data - model), W = L^-1, SLOPE_COV = L L^T per pixel

A level-2 image (``_cal``/``_calints``/``_rateints``, DN/s: the STScI pipeline's ramp fit)
enters the same likelihood as one "slope" per pixel, its rate times TGROUP (DN per group)
with its ERR: the model side applies the pipeline's estimator
(:func:`amigo.model.detector.pipeline_slope.pipeline_group_slope`) to the model's group
differences, so the brighter-fatter bending of the ramp is seen as the pipeline saw it
(:meth:`SlopeData.from_level2`).

:func:`predict_slopes` is the detector half on its own: give it any illuminance (a
visibility-injected one from the fitting engine, a uniform one for flat fields) and it
returns the slopes. :class:`SlopeData` holds one exposure's data and whitening as JAX
arrays of fixed shape (every pixel present, unused ones with a zero whitening matrix), so
that one compiled function serves every exposure with the same number of groups.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Float, Int

from amigo import niriss
from amigo.errors import InputError
from amigo.io.calslope import CalSlope, read_calslope
from amigo.io.jwst import Exposure, is_level2, read_exposure
from amigo.likelihood.pixels import ImageData, SlopeNoise, auto_structure, pipeline_groups
from amigo.likelihood.stripes import decorrelate
from amigo.model.base import BaseModel, PupilCache
from amigo.model.detector.pipeline_slope import pipeline_group_slope

TRAINING_ROLES = ("calibrator", "flat", "validation")


class SlopeData(eqx.Module):
    """One calslope exposure, ready for the likelihood.

    Attributes
    ----------
    slopes_dn
        (m, ny, nx) mean slopes, DN per group (0 where unused).
    whitening
        (ny * nx, m, m) per-pixel ``L^-1`` (zero for unused pixels), same dtype as slopes.
    used
        (ny, nx) 1.0 where the pixel enters the likelihood.
    name, filter, ngroups, role, n_values
        Static description: file stem, filter, groups, role in training, and the number
        of slope values in the likelihood.
    level2, nframes, group_time_s
        Static: whether the exposure is a level-2 image (then ``m = 1``: the pipeline's
        slope times TGROUP, see :meth:`from_level2`), its NFRAMES and TGROUP (s).
    dark_reference
        Static: the dark reference file the pipeline subtracted (level-2 images; see
        :mod:`amigo.model.detector.dark_residual`), empty otherwise.
    flat_reference
        Static: the flat-field reference file the pipeline divided by (level-2 images),
        empty otherwise: the residual sensitivity a model learns stands behind it.
    stripes
        Level-2 images: (nx, ny, ny) symmetric whitener of each column for the image's
        1/f stripes (:func:`amigo.likelihood.stripes.column_whiteners`), applied after
        the per-pixel whitening (:func:`whiten`); ``None``: no stripes (the default).
    groups_used
        Level-2 images the pipeline's charge-migration step ran on: (ny, nx) the leading
        groups of each pixel its ramp fit used
        (:func:`~amigo.model.detector.pipeline_slope.charge_loss_groups`); ``None``: all.
    """

    slopes_dn: Float[Array, "m ny nx"]
    whitening: Float[Array, "n m m"]
    used: Float[Array, "ny nx"]
    name: str = eqx.field(static=True)
    filter: str = eqx.field(static=True)
    ngroups: int = eqx.field(static=True)
    role: str = eqx.field(static=True)
    n_values: int = eqx.field(static=True)
    level2: bool = eqx.field(static=True, default=False)
    nframes: int = eqx.field(static=True, default=1)
    group_time_s: float = eqx.field(static=True, default=0.0)
    dark_reference: str = eqx.field(static=True, default="")
    flat_reference: str = eqx.field(static=True, default="")
    stripes: Float[Array, "nx ny ny"] | None = None
    groups_used: Int[Array, "ny nx"] | None = None

    @classmethod
    def from_calslope(
        cls,
        product: CalSlope,
        role: str,
        diagonal: bool = False,
        dtype: DTypeLike = jnp.float32,
    ) -> SlopeData:
        """Build from a :class:`~amigo.io.calslope.CalSlope`: the full slope covariance
        where the file averages enough integrations, the pooled estimate otherwise (as
        ``amigo fit``, :func:`~amigo.likelihood.pixels.auto_structure`); ``diagonal=True``
        ignores the covariances between a pixel's slopes."""
        if role not in TRAINING_ROLES:
            raise ValueError(f"role {role!r} not in {TRAINING_ROLES}")
        path = product.path or "<calslope>"
        m, ny, nx = product.slope_dn.shape
        if m < 1:
            raise InputError(path, "needs at least 2 groups")
        bad = product.unusable
        structure = "diagonal" if diagonal else auto_structure(product)
        noise = SlopeNoise.from_covariance(product.slope_cov_dn2, bad=bad, structure=structure)
        if noise.pixels.size == 0:
            raise InputError(path, "no usable pixel")
        whitening = np.zeros((ny * nx, m, m))
        whitening[noise.pixels] = noise.whitening
        used = np.zeros(ny * nx)
        used[noise.pixels] = 1.0
        slopes = np.where(used.reshape(ny, nx)[None] > 0, product.slope_dn, 0.0)
        header = product.primary_header
        filter_name = str(header.get("FILTER", "")).strip().upper()
        if role == "flat":
            # A flat field does not go through the optics: one compiled model serves all.
            filter_name = ""
        name = _stem(path)
        return cls(
            slopes_dn=jnp.asarray(slopes, dtype),
            whitening=jnp.asarray(whitening, dtype),
            used=jnp.asarray(used.reshape(ny, nx), dtype),
            name=name,
            filter=filter_name,
            ngroups=m + 1,
            role=role,
            n_values=int(noise.pixels.size * m),
        )

    @classmethod
    def from_level2(
        cls, exposure: Exposure, role: str, dtype: DTypeLike = jnp.float32
    ) -> SlopeData:
        """Build from a level-2 exposure (``_cal``/``_calints``/``_rateints``, DN/s).

        The image (integrations averaged as :meth:`ImageData.from_exposure` does) becomes
        one value per pixel, ``rate * TGROUP`` in DN per group, whitened by ``1 / (ERR *
        TGROUP)``. Pixels the pipeline flagged SATURATED are left out: their slope comes
        from fewer groups than the header's NGROUPS, at a level the file does not state.
        Where the pipeline's charge-migration step ran (``S_CHGMIG``), the groups it left
        out are known from its threshold and the model's ramp is fitted as the pipeline
        fitted the data's (``groups_used``). A flat field cannot be level-2 (the pipeline
        has divided it out).
        """
        meta = exposure.meta
        if role not in TRAINING_ROLES:
            raise ValueError(f"role {role!r} not in {TRAINING_ROLES}")
        if role == "flat":
            raise InputError(meta.path, "a flat field must be a calslope file, not level-2")
        if not meta.in_dn_per_s:
            raise InputError(meta.path, f"BUNIT {meta.bunit!r}: level-2 images in DN/s needed")
        if meta.ngroups < 2:
            raise InputError(meta.path, f"NGROUPS {meta.ngroups}: at least 2 groups needed")
        image = ImageData.from_exposure(exposure)  # leaves out SATURATED values
        groups = pipeline_groups(exposure)
        if not image.mask.any():
            raise InputError(meta.path, "no usable pixel")
        return cls.from_rate_image(
            image.data,
            image.error,
            image.mask,
            ngroups=int(meta.ngroups),
            group_time_s=float(meta.group_time_s),
            nframes=int(meta.nframes),
            name=_stem(meta.path),
            filter_name=str(meta.filter).strip().upper(),
            role=role,
            dtype=dtype,
            dark_reference=meta.dark_reference,
            flat_reference=meta.flat_reference,
            groups_used=None if groups is None else groups.groups,
        )

    @classmethod
    def from_rate_image(
        cls,
        rate_dn_s: np.ndarray,
        error_dn_s: np.ndarray,
        used: np.ndarray,
        *,
        ngroups: int,
        group_time_s: float,
        nframes: int = 1,
        name: str = "level2",
        filter_name: str = "F480M",
        role: str = "calibrator",
        dtype: DTypeLike = jnp.float32,
        dark_reference: str = "",
        groups_used: np.ndarray | None = None,
        flat_reference: str = "",
    ) -> SlopeData:
        """A level-2 exposure from its (ny, nx) rate and error (DN/s) and the pixels to
        use: one value per pixel, ``rate * TGROUP`` (DN per group), whitened by
        ``1 / (error * TGROUP)``; ``dark_reference`` and ``flat_reference`` name the
        pipeline's dark and flat files, ``groups_used`` the groups its ramp fit used per
        pixel (``None``: all)."""
        used = np.asarray(used, bool)
        t = float(group_time_s)
        ny, nx = used.shape
        whitening = np.zeros((ny * nx, 1, 1))
        whitening[used.ravel(), 0, 0] = 1.0 / (np.asarray(error_dn_s)[used] * t)
        slopes = np.where(used, np.asarray(rate_dn_s) * t, 0.0)[None]
        return cls(
            slopes_dn=jnp.asarray(slopes, dtype),
            whitening=jnp.asarray(whitening, dtype),
            used=jnp.asarray(used, dtype),
            name=name,
            filter=filter_name,
            ngroups=int(ngroups),
            role=role,
            n_values=int(used.sum()),
            level2=True,
            nframes=int(nframes),
            group_time_s=t,
            dark_reference=dark_reference,
            flat_reference=flat_reference,
            groups_used=None if groups_used is None else jnp.asarray(groups_used, jnp.int32),
        )

    @classmethod
    def read(
        cls,
        path: str | os.PathLike[str],
        role: str,
        diagonal: bool = False,
        dtype: DTypeLike = jnp.float32,
    ) -> SlopeData:
        """Read a calslope file or a level-2 image (raises
        :class:`~amigo.errors.InputError` if it is neither)."""
        if is_level2(path):
            data = cls.from_level2(read_exposure(path), role, dtype)
        else:
            data = cls.from_calslope(read_calslope(path), role, diagonal, dtype)
        if role != "flat" and data.filter not in niriss.CALIBRATED_FILTERS:
            raise InputError(path, f"FILTER {data.filter!r} is not a calibrated AMI filter")
        return data

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.slopes_dn.shape[1:])  # type: ignore[return-value]

    def with_stripes(self, whitener: np.ndarray | None) -> SlopeData:
        """The same exposure whitened also for its 1/f stripes: ``whitener`` (nx, ny, ny)
        from :func:`amigo.likelihood.stripes.column_whiteners` (``None``: none). Level-2
        images only (one value per pixel; a calslope file's stripes are removed by
        ``amigo process``)."""
        if whitener is None:
            return dataclasses.replace(self, stripes=None)
        if not self.level2:
            raise ValueError("stripes are marginalised in level-2 images only")
        ny, nx = self.shape
        if np.shape(whitener) != (nx, ny, ny):
            raise ValueError(f"whitener of shape {np.shape(whitener)}, not {(nx, ny, ny)}")
        return dataclasses.replace(self, stripes=jnp.asarray(whitener, self.slopes_dn.dtype))

    def layout(self) -> SlopeData:
        """The same arrays without the description the likelihood does not read (name,
        role, value count, dark and flat references): what a compiled program is keyed on, so that
        exposures of one filter and number of groups share it."""
        return dataclasses.replace(
            self, name="", role="calibrator", n_values=0, dark_reference="", flat_reference=""
        )


def _stem(path) -> str:
    """File name without ``_calslope.fits`` (or a level-2 suffix)."""
    name = Path(str(path)).name
    for suffix in ("_calslope.fits", "_calints.fits", "_rateints.fits", "_cal.fits", ".fits"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


# ---------------------------------------------------------------------------- sources


class PointSourceParams(eqx.Module):
    """Per-exposure parameters of a point source.

    Attributes
    ----------
    position_arcsec
        (2,) offset (x, y) in the optical frame from the centre of the field.
    flux_e
        Photo-electrons per integration (the whole ramp) entering the model.
    drift_nm
        ``None``, or (7, k): this exposure's wavefront drift, rms nm added to the model's
        per-hole Noll Zernikes 1..k of its filter (the telescope's wavefront moves
        between exposures; training learns the static part shared by all of them).
    drift_prior_nm
        Width of the Gaussian prior on each drift coefficient around zero ("small");
        :meth:`prior_residuals` are its whitened residuals.
    """

    position_arcsec: Float[Array, " 2"]
    flux_e: Float[Array, ""]
    drift_nm: Float[Array, "7 k"] | None = None
    drift_prior_nm: float = eqx.field(static=True, default=0.0)

    def with_drift(self, modes: int, prior_nm: float) -> PointSourceParams:
        """The same source with a zero drift of the first ``modes`` Zernikes per hole
        under a prior of ``prior_nm`` (``modes`` 0: none)."""
        if modes <= 0:
            return PointSourceParams(self.position_arcsec, self.flux_e)
        if prior_nm <= 0:
            raise ValueError("a wavefront drift needs a prior width > 0 nm")
        drift = jnp.zeros((niriss.N_HOLES, modes), self.flux_e.dtype)
        return PointSourceParams(self.position_arcsec, self.flux_e, drift, float(prior_nm))

    def prior_residuals(self) -> Array:
        """Whitened residuals of the drift's prior, (7 k,) (empty without a drift): their
        squares' half sum is the prior's term of the loss."""
        if self.drift_nm is None:
            return jnp.zeros((0,), self.flux_e.dtype)
        return (self.drift_nm / self.drift_prior_nm).ravel()

    def n_free(self) -> int:
        """The parameters a fit of this exposure spends: position (2), flux, drift."""
        return 3 + (0 if self.drift_nm is None else int(self.drift_nm.size))


class FlatParams(eqx.Module):
    """Per-exposure parameter of a flat field: electrons per pixel per integration."""

    level_e: Float[Array, ""]

    def prior_residuals(self) -> Array:
        """No prior (as :meth:`PointSourceParams.prior_residuals` without a drift)."""
        return jnp.zeros((0,), self.level_e.dtype)

    def n_free(self) -> int:
        """The parameters a fit of this exposure spends: its level."""
        return 1


def predict_slopes(
    base: BaseModel, illuminance_e: Float[Array, "m m"], ngroups: int
) -> Float[Array, "g ny nx"]:
    """Slopes (ngroups - 1, ny, nx) in DN per group from an illuminance in photo-electrons
    per integration on the detector's 3x grid (the detector half of the model)."""
    return base.slopes(illuminance_e, ngroups)


def point_source_slopes(
    base: BaseModel, cache: PupilCache, params: PointSourceParams, data: SlopeData
) -> Array:
    """Model slopes of a point source for the exposure ``data`` (its filter and groups);
    for a level-2 image, (1, ny, nx): the pipeline's slope of the model ramp."""
    if params.drift_nm is not None:
        modes = params.drift_nm.shape[1]
        zernikes = base.zernikes_nm[data.filter].at[:, :modes].add(params.drift_nm)
        base = eqx.tree_at(lambda m: m.zernikes_nm[data.filter], base, zernikes)
    unit = base.illuminance(data.filter, params.position_arcsec, cache)
    slopes = predict_slopes(base, params.flux_e * unit, data.ngroups)
    if data.level2:
        gain = base.read.gain_e_per_dn
        return pipeline_group_slope(
            slopes, data.group_time_s, gain, data.nframes, data.groups_used
        )[None]
    return slopes


def flat_slopes(base: BaseModel, params: FlatParams, data: SlopeData) -> Array:
    """Model slopes of a uniformly illuminated (flat-field) exposure."""
    ny, nx = data.shape
    dtype = data.slopes_dn.dtype
    uniform = jnp.full((3 * ny, 3 * nx), params.level_e / 9.0, dtype)
    return predict_slopes(base, uniform, data.ngroups)


def model_slopes(
    base: BaseModel, cache: PupilCache, params: PointSourceParams | FlatParams, data: SlopeData
) -> Array:
    """Model slopes of any exposure (point source or flat field)."""
    if isinstance(params, FlatParams):
        return flat_slopes(base, params, data)
    return point_source_slopes(base, cache, params, data)


# ---------------------------------------------------------------------------- likelihood


def whiten(values_dn: Float[Array, "m ny nx"], data: SlopeData) -> Array:
    """(ny * nx, m) ``W v`` per pixel (zero rows for unused pixels): slopes, or a change
    of the model slopes, in units of the noise; for a level-2 image with stripes
    (:meth:`SlopeData.with_stripes`) whitened again along each column, so that
    ``|whiten(r)|^2 = r^T C^-1 r`` with the stripes' covariance in ``C``."""
    m = data.slopes_dn.shape[0]
    z = jnp.einsum("nij,nj->ni", data.whitening, values_dn.reshape(m, -1).T)
    if data.stripes is None:
        return z
    ny, nx = data.shape
    return decorrelate(z.reshape(ny, nx), data.stripes).reshape(ny * nx, 1)


def whitened_residuals(model_dn: Float[Array, "m ny nx"], data: SlopeData) -> Array:
    """(ny * nx, m) ``W (data - model)`` per pixel; zero rows for unused pixels."""
    return whiten(data.slopes_dn - model_dn, data)


def chi2(model_dn: Array, data: SlopeData) -> Array:
    """Chi-square of the slopes (the log-likelihood is ``-chi2 / 2`` + a constant)."""
    return jnp.sum(whitened_residuals(model_dn, data) ** 2)


@dataclass(frozen=True)
class FitStatistics:
    """Summary of a fit, as in ``fit_summary.json``."""

    name: str
    filter: str
    role: str
    ngroups: int
    npix: int
    chi2: float
    dof: int
    zscore_std: float
    zscore_std_whitened: float | None = None

    def to_json(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


def fit_statistics(
    model_dn: Array, data: SlopeData, n_free: int = 0, role: str | None = None
) -> FitStatistics:
    """Chi-square (the likelihood's: whitened for the stripes where the image has them),
    degrees of freedom and z-score standard deviation (over used values; plain, ``(data
    - model) / err``, as ``amigo fit``'s ``zscore_std``, and with stripes whitened for
    them too, ``zscore_std_whitened``)."""
    used = np.asarray(data.used).reshape(-1) > 0
    z = np.asarray(whitened_residuals(model_dn, data), dtype=np.float64)
    values = z[used].ravel()
    whitened = None
    if data.stripes is not None:
        whitened = float(np.std(values))
        plain = np.asarray(whitened_residuals(model_dn, data.with_stripes(None)), np.float64)
        z_std = float(np.std(plain[used].ravel()))
    else:
        z_std = float(np.std(values))
    return FitStatistics(
        name=data.name,
        filter=data.filter,
        role=role or data.role,
        ngroups=data.ngroups,
        npix=int(used.sum()),
        chi2=float(np.sum(values**2)),
        dof=int(values.size - n_free),
        zscore_std=z_std,
        zscore_std_whitened=whitened,
    )


# ---------------------------------------------------------------------------- starting values


def initial_point_source(
    base: BaseModel, data: SlopeData, fraction_in_field: float = 0.9
) -> PointSourceParams:
    """Starting position (centroid of the summed slopes) and flux (their total)."""
    image = np.asarray(data.slopes_dn).sum(axis=0) * np.asarray(data.used)
    image = np.clip(image, 0.0, None)
    ny, nx = image.shape
    yy, xx = np.mgrid[:ny, :nx]
    # Centroid of the bright core only: the AMI envelope is symmetric about the source.
    core = image * (image > 0.05 * image.max())
    cx = float((core * xx).sum() / core.sum()) - 0.5 * (nx - 1)
    cy = float((core * yy).sum() / core.sum()) - 0.5 * (ny - 1)
    position = base.detector.detector_to_optical(jnp.array([cx, cy]))
    # Mean DN per group times the groups: the integration's charge.
    total_dn = image.sum() / data.slopes_dn.shape[0] * data.ngroups
    flux = total_dn * base.read.gain_e_per_dn / fraction_in_field
    dtype = data.slopes_dn.dtype
    return PointSourceParams(jnp.asarray(position, dtype), jnp.asarray(flux, dtype))


def initial_flat(base: BaseModel, data: SlopeData) -> FlatParams:
    """Starting level: the median slope per group times the groups, in electrons."""
    slopes = np.asarray(data.slopes_dn).sum(axis=0)[np.asarray(data.used) > 0]
    level = np.median(slopes) * data.ngroups / (data.ngroups - 1) * base.read.gain_e_per_dn
    return FlatParams(jnp.asarray(level, data.slopes_dn.dtype))


def initial_params(base: BaseModel, data: SlopeData) -> PointSourceParams | FlatParams:
    """Starting parameters for any exposure."""
    if data.role == "flat":
        return initial_flat(base, data)
    return initial_point_source(base, data)
