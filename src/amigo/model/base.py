"""The base model: the trained state of the whole instrument, and its file format.

The paper's "Base Model Training and Calibration" produces one object that every fit
starts from: the optics (per-filter aberrations and defocus, the mask's hole positions),
the linear detector (jitter, rotation, anisotropy), the non-linear ramp model (the
charge-migration network, the flat field, the intra-pixel response) and the read model
(dark current, IPC, per-pixel non-linearity, gain). :class:`BaseModel` is that object, as
one equinox module whose array leaves are the parameters.

Parameters and what trains them (see :mod:`amigo.training.trainer`)::

    zernikes_nm[filter]    (7, 10)  per-hole Noll Zernikes, rms OPD nm     physical
    defocus_nm[filter]     ()       Fresnel defocus, Noll Z4 rms nm        physical
    hole_centres_m         (7, 2)   hole centres on the mask, m            physical
    hole_sizes_m           (7,)     hole sizes (flat to flat) on the mask, m physical
    detector               LinearDetector: jitter, rotation, anisotropy   physical
    ramp.intra_pixel       (5,)     quadratic intra-pixel response         physical
    read.dark_e_per_group  (80, 80) dark current per pixel, e- per group   dark (calibrators)
    ramp.network           8,640 CNN weights                               network
    ramp.flat              (80, 80) inter-pixel sensitivity                pixel (flats only)
    read.nonlinearity      (80, 80) quadratic non-linearity, 1/e-          pixel (flats only)
    read.ipc_kernel        (5, 5)   CRDS kernel                            fixed
    read.group_offsets_dn  (G, 80, 80) level-2 models: what the pipeline's dark   solved after
                                    subtraction left in each group read, DN   training
    read.group_offsets_chol_dn (G, G, 80, 80) their posterior's Cholesky factor   solved after
                                    (DN): the uncertainty they leave             training
    read.superbias_dn      (80, 80) models of raw ramps: each pixel's reset     measured on
                                    level, DN (``amigo train --darks``)           darks
    read.superbias_var_dn2 (80, 80) its variance, DN^2                          "

File format (``.npz``, readable with ``numpy.load(path, allow_pickle=False)``)
------------------------------------------------------------------------------
* one array per parameter leaf, keyed by its path in the module, e.g.
  ``.zernikes_nm['F430M']``, ``.ramp.network.layers[2].weight``, ``.read.nonlinearity``,
  stored in the dtype it was trained in (float32 or float64), so a round trip is exact;
* ``__metadata__``: a 0-d unicode array holding a JSON record: ``format`` and
  ``format_version``, ``config`` (everything needed to rebuild the module's skeleton and
  its static settings), and free-form provenance (training data, scenario, seeds,
  versions, losses, dtype, date, time and machine of training).

Nothing is pickled: :func:`load_base_model` rebuilds the skeleton from ``config`` and
fills in the arrays by path, refusing files whose paths or shapes do not match.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from numpy.lib.npyio import NpzFile

from amigo import niriss
from amigo.errors import InputError
from amigo.io.atomic import atomic_path
from amigo.io.files import DAMAGE, is_number, require_file
from amigo.model.detector.boundary import BoundaryShift
from amigo.model.detector.dark_residual import level2_offset_response, offset_variance
from amigo.model.detector.linear import LinearDetector
from amigo.model.detector.ramp import (
    DEFAULT_CHARGE_SCALE_E,
    DEFAULT_MAX_SHIFT_PIX,
    ChargeMigrationNetwork,
    IntraPixelResponse,
    RampModel,
)
from amigo.model.detector.read import ReadModel, default_ipc_kernel
from amigo.model.detector.reset import Superbias
from amigo.model.optics.aperture import PupilGrid, soft_hexagon, zernike_basis
from amigo.model.optics.model import NRMOptics, OpticsConfig
from amigo.model.optics.spectrum import LinearSpectrum

FORMAT = "amigo-base-model"
#: 2: the dark current is a per-pixel map (version 1 held one value for all pixels);
#: 3: the SIAF's detector geometry (see GEOMETRY_KEYS); 4: the hole sizes are parameters;
#: 5: level-2 models may hold per-group read offsets (``dark_residual_groups`` > 0);
#: 6: and their posterior uncertainty (``dark_prior_dn`` > 0, ``read.group_offsets_chol_dn``);
#: 7: models of raw ramps may hold a superbias (``superbias_files`` > 0).
FORMAT_VERSION = 7
#: Leaves of the linear detector's geometry (format 3 added skew and scale, and the SIAF's
#: sense of rotation).
GEOMETRY_KEYS = (
    ".detector.rotation_deg",
    ".detector.anisotropy",
    ".detector.skew_deg",
    ".detector.scale",
)
METADATA_KEY = "__metadata__"
DARK_KEY = ".read.dark_e_per_group"
#: Hole sizes, fitted since format 4 (older files take the nominal 0.80 m for every hole).
HOLE_SIZES_KEY = ".hole_sizes_m"
#: Package-data location of the shipped base model.
DEFAULT_MODEL_RESOURCE = ("data", "base_model", "amigo_base_model.npz")
#: Package-data location of the base model trained on real level-2 calibrator images (the
#: default of ``amigo fit`` for level-2 images when it is shipped).
LEVEL2_MODEL_RESOURCE = ("data", "base_model", "amigo_base_model_com1093_level2.npz")
#: Settings of :class:`BaseModelConfig` that only set how finely the optics is computed.
OPTICS_SETTINGS = ("pupil_npix", "n_wavelengths", "defocus_method")


#: Accepted ranges of a model file's numeric settings (well beyond any trained model's).
CONFIG_LIMITS: dict[str, tuple[float, float]] = {
    "pupil_npix": (16, 2048),
    "n_wavelengths": (1, 64),
    "n_zernike": (1, 66),
    "n_substeps": (1, 64),
    "network_width": (1, 256),
    "network_depth": (1, 16),
    "dark_residual_groups": (0, 256),
    "superbias_files": (0, 10**6),
    "gain_e_per_dn": (0.01, 100.0),
    "max_shift_pix": (0.0, 10.0),
    "charge_scale_e": (1.0, 1e9),
    "dark_prior_dn": (0.0, 1e6),
}


#: What reading a damaged ``.npz`` raises besides :data:`~amigo.io.files.DAMAGE`: the zip
#: layer's errors, those of the compressed stream, and of NumPy's parser of a damaged
#: ``.npy`` header (a Python literal), and the zip module's for a compression method field
#: it does not know.
NPZ_DAMAGE = (
    *DAMAGE, zipfile.BadZipFile, zlib.error, EOFError, OSError, SyntaxError, tokenize.TokenError,
    NotImplementedError,
)  # fmt: skip


@dataclass(frozen=True)
class BaseModelConfig:
    """Static settings of a base model (stored in the file; hashable).

    Attributes
    ----------
    filters
        Filters with their own optics state.
    shape
        Detector pixels (ny, nx).
    pupil_npix
        Pupil pixels across the JWST pupil diameter (sampling of the mask). 256 (2.5 cm,
        31 across a hole): fitted to a noiseless image of the simulator's 512-pixel
        optics with the noise of a CAL 4481-depth F380M exposure, the best chi2 left by
        the optics alone is 2.7e3 over 6,080 pixels at 256 and 1.6e4 at 128 (the
        residual follows the outer lobes of the hole envelope, where the sampled hole
        edges matter; docs/detector.md).
    n_wavelengths
        Wavelength bins per filter.
    n_zernike
        Noll Zernikes per hole.
    n_substeps
        Recurrent sub-steps of the ramp model.
    max_shift_pix, charge_scale_e, network_width, network_depth
        Settings of the charge-migration network (see :mod:`amigo.model.detector.ramp`).
    gain_e_per_dn
        Gain (not trained: it is degenerate with the flux).
    defocus_method
        How the optics applies the Fresnel defocus (see :class:`amigo.model.optics.OpticsConfig`).
        ``"pupil"`` (the quadratic OPD in the pupil) is exact for a defocus and free;
        ``"angular_spectrum"`` (the paper's, applied to the finite focal field) gave the
        same fidelity floor at several times the cost of the image (docs/detector.md, "Optics
        fidelity: why a 256-pixel pupil").
        Files written before these defaults record 128 and ``"angular_spectrum"``.
    data_level
        What the detector half describes. ``"ramp"`` (trained on raw ramps, calslope
        files): the flat field, dark current and non-linearity are the detector's own.
        ``"level2"`` (trained on the STScI pipeline's level-2 images): the pipeline has
        subtracted the dark, divided by its flat and linearised, so dark and
        non-linearity are zero and the flat is the *residual* pixel response the
        pipeline's flat leaves (:meth:`BaseModel.for_level2`).
    dark_residual_groups, dark_reference
        Level-2 models: the number ``G`` of group reads whose per-pixel offsets the model
        holds (``read.group_offsets_dn``, what the pipeline's dark subtraction left; 0:
        none), and the dark reference file (the level-2 header's ``R_DARK``) they were
        measured behind: they describe that file's noise, so they apply only to images
        processed with it (:mod:`amigo.model.detector.dark_residual`).
    dark_prior_dn
        Level-2 models: the prior width (DN) of each read's offset that the solve used;
        with the posterior it left (``read.group_offsets_chol_dn``) it gives the variance
        the offsets the model does not know add to an image
        (:meth:`BaseModel.dark_offset_terms`). 0 (files before format 6): none added.
    superbias_files
        Models of raw ramps: the number of dark calslope files the superbias
        (``read.superbias_dn``, ``read.superbias_var_dn2``) was measured on; 0 (and files
        before format 7): the model holds none.
    """

    filters: tuple[str, ...] = niriss.CALIBRATED_FILTERS
    shape: tuple[int, int] = (niriss.SUBARRAY_SIZE, niriss.SUBARRAY_SIZE)
    pupil_npix: int = 256
    n_wavelengths: int = 9
    n_zernike: int = 10
    n_substeps: int = 8
    max_shift_pix: float = DEFAULT_MAX_SHIFT_PIX
    charge_scale_e: float = DEFAULT_CHARGE_SCALE_E
    network_width: int = 16
    network_depth: int = 3
    gain_e_per_dn: float = niriss.GAIN_E_PER_DN
    defocus_method: str = "pupil"
    data_level: str = "ramp"
    dark_residual_groups: int = 0
    dark_reference: str = ""
    dark_prior_dn: float = 0.0
    superbias_files: int = 0

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> BaseModelConfig:
        """The config of a model file's record; ``ValueError`` naming the first setting of
        the wrong type or outside :data:`CONFIG_LIMITS` (a damaged or tampered file must
        not make the loader allocate without bound)."""
        if not isinstance(record, dict):
            raise ValueError(f"config is {type(record).__name__}, not a mapping")
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in record.items() if k in known}
        for key in ("filters", "shape"):
            if key in values:
                if not isinstance(values[key], list | tuple):
                    raise ValueError(f"config {key} is {values[key]!r}, not a list")
                values[key] = tuple(values[key])
        default = cls()
        for key, value in values.items():
            expected = type(getattr(default, key))
            ok = isinstance(value, expected) and not (expected is int and isinstance(value, bool))
            if expected is float:
                ok = is_number(value) and math.isfinite(value)
            if not ok:
                raise ValueError(f"config {key} is {value!r}, not a {expected.__name__}")
            if key in CONFIG_LIMITS and not CONFIG_LIMITS[key][0] <= value <= CONFIG_LIMITS[key][1]:
                raise ValueError(f"config {key} is {value!r}, outside {CONFIG_LIMITS[key]}")
        if "shape" in values and not (
            len(values["shape"]) == 2
            and all(isinstance(n, int) and 8 <= n <= 2048 for n in values["shape"])
        ):
            raise ValueError(f"config shape is {values['shape']!r}")
        if "filters" in values and not all(f in niriss.FILTERS for f in values["filters"]):
            raise ValueError(f"config filters {values['filters']!r} are not NIRISS AMI filters")
        return cls(**values)

    def optics_config(self) -> OpticsConfig:
        # Pinned here, not taken from the optics' defaults: a model must predict what it
        # was trained to predict whatever those defaults become.
        return OpticsConfig(
            npix_detector=self.shape[0],
            pupil_npix=self.pupil_npix,
            n_zernike=self.n_zernike,
            defocus_method=self.defocus_method,
        )


class MovableHoles(eqx.Module):
    """The mask with fittable hole centres and sizes and a fixed (precomputed) Zernike basis.

    Implements the aperture interface of :class:`amigo.model.optics.NRMOptics`
    (``hole_transmissions``, ``zernike_basis``). The hexagons (flat to flat ``sizes_m``)
    are drawn at ``centres_m``
    on every call (soft edges, so the image is differentiable in the centres); the
    Zernike basis stays on the nominal centres, because the wavefront belongs to the
    telescope, not to the mask.
    """

    centres_m: Float[Array, "7 2"]
    sizes_m: Float[Array, " 7"]
    basis: Float[Array, "7 j ny nx"]

    def hole_transmissions(
        self, grid: PupilGrid, softening_px: float = 1.0, supersample: int = 1
    ) -> Array:
        """(7, ny, nx) soft-edged hexagons at ``centres_m``; with ``supersample`` > 1 each
        pixel is the mean of ``supersample^2`` sub-samples (as the optics' aperture)."""
        x, y = grid.coordinates()
        edge = softening_px * grid.pixel_m / supersample
        size = self.sizes_m.astype(x.dtype)[:, None, None]  # flat to flat, per hole
        offsets = (np.arange(supersample) - 0.5 * (supersample - 1)) / supersample * grid.pixel_m
        # The seven holes broadcast along a leading axis, not a Python loop: one copy of
        # the hexagon's graph instead of seven (compile time, which dominates on a CPU).
        cx = self.centres_m[:, 0, None, None]
        cy = self.centres_m[:, 1, None, None]
        total: float | Array = 0.0
        for oy in offsets:
            for ox in offsets:
                total = total + soft_hexagon(x + ox - cx, y + oy - cy, size, edge)
        return cast(Array, total) / supersample**2  # an Array: supersample >= 1

    def zernike_basis(self, grid: PupilGrid, n_modes: int, radius_factor: float) -> Array:
        del grid, radius_factor
        if n_modes != self.basis.shape[1]:
            raise ValueError(f"basis has {self.basis.shape[1]} modes, not {n_modes}")
        return self.basis


class PupilCache(eqx.Module):
    """Parameter-free arrays derived from the configuration: the pupil grid and the
    per-hole Zernike basis (7, n_zernike, ny, nx). Build once with
    :meth:`BaseModel.pupil_cache` and pass to the forward model (it is far too large to
    store in the model file, and is recomputed exactly from the config)."""

    grid: PupilGrid
    basis: Float[Array, "7 j ny nx"]


class BaseModel(eqx.Module):
    """The trained instrument state (see the module docstring for the parameters).

    Build a fresh (untrained) one with :meth:`create`, read one with
    :func:`load_base_model`, write one with :func:`save_base_model`.
    """

    zernikes_nm: dict[str, Float[Array, "7 nz"]]
    defocus_nm: dict[str, Float[Array, ""]]
    hole_centres_m: Float[Array, "7 2"]
    hole_sizes_m: Float[Array, " 7"]
    detector: LinearDetector
    ramp: RampModel
    read: ReadModel
    config: BaseModelConfig = eqx.field(static=True)

    @classmethod
    def create(
        cls,
        config: BaseModelConfig | None = None,
        key: jax.Array | None = None,
        linear: bool = False,
        network_init_scale: float = 0.1,
    ) -> BaseModel:
        """An untrained model: nominal mask, no aberrations, the paper's detector
        geometry, unit flat, linear read-out, new network weights (``key``)."""
        config = config or BaseModelConfig()
        key = jax.random.PRNGKey(0) if key is None else key
        network = None
        if not linear:
            network = ChargeMigrationNetwork(
                key,
                width=config.network_width,
                depth=config.network_depth,
                charge_scale_e=config.charge_scale_e,
                init_scale=network_init_scale,
            )
        ramp = RampModel(
            network=network,
            flat=jnp.ones(config.shape),
            intra_pixel=IntraPixelResponse(),
            n_substeps=config.n_substeps,
            max_shift_pix=config.max_shift_pix,
        )
        offsets = chol = None
        if config.dark_residual_groups > 0:
            offsets = jnp.zeros((config.dark_residual_groups, *config.shape))
            if config.dark_prior_dn > 0:
                g = config.dark_residual_groups
                chol = jnp.zeros((g, g, *config.shape))
        level = variance = None
        if config.superbias_files > 0:
            level, variance = jnp.zeros(config.shape), jnp.zeros(config.shape)
        read = ReadModel(
            dark_e_per_group=jnp.zeros(config.shape),
            ipc_kernel=jnp.asarray(default_ipc_kernel()),
            nonlinearity=jnp.zeros(config.shape),
            gain_e_per_dn=config.gain_e_per_dn,
            group_offsets_dn=offsets,
            group_offsets_chol_dn=chol,
            superbias_dn=level,
            superbias_var_dn2=variance,
        )
        return cls(
            zernikes_nm={f: jnp.zeros((niriss.N_HOLES, config.n_zernike)) for f in config.filters},
            defocus_nm={f: jnp.asarray(0.0) for f in config.filters},
            hole_centres_m=jnp.asarray(np.asarray(niriss.HOLE_CENTRES_M, dtype=float)),
            hole_sizes_m=jnp.full(niriss.N_HOLES, float(niriss.HOLE_FLAT_TO_FLAT_M)),
            # IPC acts in the read model (on every group read), not on the linear image.
            detector=LinearDetector.create(ipc=False),
            ramp=ramp,
            read=read,
            config=config,
        )

    # ------------------------------------------------------------------ structure
    @property
    def linear(self) -> bool:
        """True when the charge-migration network is off (linear charge accumulation)."""
        return self.ramp.network is None

    @property
    def detector_mode(self) -> str:
        """What ``--detector`` names this ramp: ``"linear"`` (no charge migration),
        ``"boundary"`` (the physical account) or ``"full"`` (the network)."""
        if self.linear:
            return "linear"
        return "boundary" if isinstance(self.ramp.network, BoundaryShift) else "full"

    def with_config(self, **changes: Any) -> BaseModel:
        """The same parameters under other optics settings: ``pupil_npix``,
        ``n_wavelengths`` or ``defocus_method`` (how finely the image is computed; the
        parameters keep their meaning). Other settings fix parameter shapes or the
        detector model: ``ValueError``."""
        refused = sorted(set(changes) - set(OPTICS_SETTINGS))
        if refused:
            raise ValueError(
                f"only the optics settings {', '.join(OPTICS_SETTINGS)} can change, "
                f"not {', '.join(refused)}"
            )
        return dataclasses.replace(self, config=dataclasses.replace(self.config, **changes))

    def with_linear_detector(self) -> BaseModel:
        """The same instrument with the network switched off (``--detector linear``)."""
        return eqx.tree_at(lambda m: m.ramp.network, self, None, is_leaf=lambda x: x is None)

    def with_migration_scale(self, scale: float) -> BaseModel:
        """The same instrument with the network's charge migration scaled by ``scale``
        (0: none, 1: as trained): its last layer's weights times ``scale``. The network
        has no biases, so every sub-pixel displacement the network predicts is ``scale``
        times the trained one before the bound (``max_shift_pix tanh(s / max_shift_pix)``),
        and the charge moved follows it in proportion while displacements stay well
        inside the bound (a few hundredths of a pixel in AMI data)."""
        network = self.ramp.network
        if network is None:
            raise ValueError("the linear detector has no charge migration to scale")
        if isinstance(network, BoundaryShift):  # its strength exactly (the charge moved to
            # within the shift's guard, src/amigo/model/detector/boundary.py)
            return self.with_network(network.scaled(scale))
        last = network.layers[-1].weight
        return eqx.tree_at(lambda m: m.ramp.network.layers[-1].weight, self, last * scale)

    def for_level2(self) -> BaseModel:
        """The detector as it stands behind a level-2 image: the STScI pipeline has
        subtracted the dark, divided by its flat and corrected the classical
        non-linearity, so those are switched off (unit flat, no dark, no quadratic
        term); the charge migration (brighter-fatter), the intra-pixel response and IPC,
        which the pipeline leaves in, stay. The superbias goes (the pipeline subtracted
        the bias too).

        A model trained on level-2 images (``config.data_level == "level2"``) is returned
        as it is: its flat is the residual response behind the pipeline's flat."""
        if self.config.data_level == "level2":
            return self
        behind = eqx.tree_at(
            lambda m: (m.ramp.flat, m.read.dark_e_per_group, m.read.nonlinearity),
            self.with_superbias(None),
            (
                jnp.ones_like(self.ramp.flat),
                jnp.zeros_like(self.read.dark_e_per_group),
                jnp.zeros_like(self.read.nonlinearity),
            ),
        )
        return dataclasses.replace(
            behind, config=dataclasses.replace(behind.config, data_level="level2")
        )

    def with_dark_residual(
        self,
        offsets_dn: Float[Array, "G ny nx"] | np.ndarray | None,
        reference: str = "",
        posterior_cholesky: Float[Array, "G G ny nx"] | np.ndarray | None = None,
        prior_dn: float | None = None,
    ) -> BaseModel:
        """The same instrument with per-group read offsets (``None``: none), measured
        behind the dark reference file ``reference``, with the Cholesky factor of their
        posterior covariance and the prior width (DN) of the solve (``None``: keep this
        model's; see :class:`BaseModelConfig`)."""
        groups = 0 if offsets_dn is None else int(offsets_dn.shape[0])
        if groups and self.config.data_level != "level2":
            raise ValueError("per-group read offsets describe level-2 images only")
        if posterior_cholesky is not None and posterior_cholesky.shape[:2] != (groups, groups):
            raise ValueError(f"posterior factor {posterior_cholesky.shape} for {groups} reads")
        dtype = self.ramp.flat.dtype
        model = eqx.tree_at(
            lambda m: (m.read.group_offsets_dn, m.read.group_offsets_chol_dn),
            self,
            (
                None if offsets_dn is None else jnp.asarray(offsets_dn, dtype),
                None if posterior_cholesky is None else jnp.asarray(posterior_cholesky, dtype),
            ),
            is_leaf=lambda x: x is None,
        )
        config = dataclasses.replace(
            self.config,
            dark_residual_groups=groups,
            dark_reference=reference if groups else "",
            dark_prior_dn=self.config.dark_prior_dn if prior_dn is None else float(prior_dn),
        )
        return dataclasses.replace(model, config=config)

    def with_superbias(self, superbias: Superbias | None) -> BaseModel:
        """The model holding ``superbias`` (``None``: none); refused for a level-2 model
        (the pipeline has subtracted the bias: its images have no first read)."""
        if superbias is not None and self.config.data_level == "level2":
            raise ValueError("a level-2 model cannot hold a superbias")
        dtype = self.ramp.flat.dtype
        level = variance = None
        if superbias is not None:
            level = jnp.asarray(superbias.level_dn, dtype)
            variance = jnp.asarray(superbias.variance_dn2, dtype)
        model = eqx.tree_at(
            lambda m: (m.read.superbias_dn, m.read.superbias_var_dn2),
            self,
            (level, variance),
            is_leaf=lambda x: x is None,
        )
        files = 0 if superbias is None else max(1, int(superbias.n_files))
        return dataclasses.replace(
            model, config=dataclasses.replace(self.config, superbias_files=files)
        )

    @property
    def superbias(self) -> Superbias | None:
        """The reset level the model holds (``amigo train --darks``), or ``None``."""
        read = self.read
        if read.superbias_dn is None or read.superbias_var_dn2 is None:
            return None
        stored = Superbias(
            np.asarray(read.superbias_dn, np.float64),
            np.asarray(read.superbias_var_dn2, np.float64),
            n_files=self.config.superbias_files,
        )
        # The exact "unknown" sentinel again (float32 storage rounded it).
        return Superbias.where_known(
            stored.level_dn, stored.variance_dn2, stored.known, stored.n_files
        )

    def dark_residual_for(self, reference: str | None) -> BaseModel:
        """The model for an image processed with the dark reference ``reference`` (its
        ``R_DARK``): this one where its read offsets were measured behind that file, else
        the same without them (they describe another file's noise; its prior width stays,
        for :meth:`dark_offset_terms`)."""
        if self.config.dark_residual_groups == 0 or reference == self.config.dark_reference:
            return self
        return self.with_dark_residual(None)

    def dark_offset_terms(
        self,
        reference: str,
        rate_dn_s: Float[Array, "ny nx"] | np.ndarray,
        ngroups: int,
        group_time_s: float,
        nframes: int = 1,
        groups_used: np.ndarray | None = None,
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """``(pattern, variance)`` of this model's read offsets in a level-2 image of
        ``rate_dn_s`` taken with ``ngroups`` reads behind the dark reference
        ``reference``, both (ny, nx), from the pipeline's response to each read at the
        image's own rate (:func:`~amigo.model.detector.dark_residual.level2_offset_response`;
        over the groups it fitted, ``groups_used`` per pixel, ``None`` for all).

        ``pattern`` (DN/s): what the offsets the model holds add to the image; ``None``
        where they do not apply (another reference, none held). ``variance`` ((DN/s)^2):
        what the offsets the model does not know add
        (:func:`~amigo.model.detector.dark_residual.offset_variance`): the posterior's behind
        the file the offsets were measured behind, the prior's behind another; zero where
        the pipeline subtracted no dark (``reference`` empty) or the model records no
        prior (files before format 6).
        """
        zeros = np.zeros(np.shape(rate_dn_s))
        if not reference or ngroups < 2 or self.config.data_level != "level2":
            return None, zeros
        read = self.dark_residual_for(reference).read
        prior = self.config.dark_prior_dn
        if read.group_offsets_dn is None and prior <= 0:
            return None, zeros
        response = level2_offset_response(
            rate_dn_s, ngroups, group_time_s, self.read.gain_e_per_dn, nframes, groups_used
        )
        pattern = None
        if read.group_offsets_dn is not None:
            offsets = np.asarray(read.group_offsets_dn, np.float64)
            n = min(ngroups, offsets.shape[0])
            pattern = np.einsum("gyx,gyx->yx", response[:n], offsets[:n]) / group_time_s
        variance = zeros
        if prior > 0:
            chol_dn = read.group_offsets_chol_dn
            chol = None if chol_dn is None else np.asarray(chol_dn)
            variance = offset_variance(response, prior, chol) / group_time_s**2
        return pattern, variance

    def with_network(self, network: ChargeMigrationNetwork | BoundaryShift | None) -> BaseModel:
        """The same instrument with another network (``None``: linear; a
        :class:`BoundaryShift`: the physical account of ``--detector boundary``)."""
        return eqx.tree_at(lambda m: m.ramp.network, self, network, is_leaf=lambda x: x is None)

    @property
    def n_parameters(self) -> int:
        """Number of scalar parameters (every array leaf, the fixed IPC kernel included)."""
        return sum(int(np.size(x)) for x in jax.tree.leaves(eqx.filter(self, eqx.is_array)))

    def check_filter(self, filter_name: str) -> str:
        if filter_name not in self.zernikes_nm:
            raise ValueError(
                f"the base model has no optics state for {filter_name} "
                f"(it has {', '.join(self.zernikes_nm)})"
            )
        return filter_name

    # ------------------------------------------------------------------ optics
    def pupil_cache(self) -> PupilCache:
        """The pupil grid and Zernike basis for this configuration (compute once)."""
        c = self.config.optics_config()
        grid = PupilGrid.for_mask(c.pupil_npix, c.pupil_diameter_m)
        radius = c.zernike_radius_factor * niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3.0)
        centres = np.asarray(niriss.HOLE_CENTRES_M)
        basis = jax.jit(functools.partial(_basis, centres=centres, radius=radius, n=c.n_zernike))(
            grid
        )
        return PupilCache(grid=grid, basis=basis)

    def optics(self, filter_name: str, cache: PupilCache) -> NRMOptics:
        """The optical model of one filter (an :class:`amigo.model.optics.NRMOptics`)."""
        self.check_filter(filter_name)
        holes = MovableHoles(
            centres_m=self.hole_centres_m,
            sizes_m=self.hole_sizes_m,
            basis=cache.basis.astype(self.hole_centres_m.dtype),
        )
        return NRMOptics(
            aperture=holes,
            zernikes_nm=self.zernikes_nm[filter_name],
            defocus_nm=self.defocus_nm[filter_name],
            hole_amplitudes=jnp.ones(niriss.N_HOLES, self.hole_centres_m.dtype),
            grid=cache.grid,
            config=self.config.optics_config(),
        )

    def spectrum(self, filter_name: str, slope_per_um: float = 0.0) -> LinearSpectrum:
        """The filter's default spectrum at the model's wavelength sampling."""
        return _filter_spectrum(filter_name, self.config.n_wavelengths, float(slope_per_um))

    # Compiled as one program (filter name static): op by op, the optics and the
    # resampling cost minutes of per-primitive tracing outside a caller's jit.
    @eqx.filter_jit
    def illuminance(
        self,
        filter_name: str,
        position_arcsec: Float[Array, " 2"],
        cache: PupilCache,
        spectrum: LinearSpectrum | None = None,
    ) -> Float[Array, "m m"]:
        """Unit-flux illuminance of a point source on the detector's 3x grid, (240, 240).

        Optics (pupil, aberrations, Fresnel defocus, MFT, pixel integration), then the
        linear detector's jitter and rotation/anisotropy resampling. Multiply by the
        flux in electrons per integration to feed :meth:`slopes`.
        """
        spectrum = self.spectrum(filter_name) if spectrum is None else spectrum
        image = self.optics(filter_name, cache).illuminance(spectrum, position_arcsec)
        return self.detector.illuminance(image)

    # ------------------------------------------------------------------ detector
    @eqx.filter_jit
    def slopes(self, illuminance_e: Float[Array, "m m"], ngroups: int) -> Float[Array, "g y x"]:
        """Predicted slopes (ngroups - 1, ny, nx), DN per group, from an illuminance in
        photo-electrons per integration on the 3x grid: ramp model -> read model ->
        group differences. This is where a visibility-injected illuminance (issue 4)
        plugs in front of the detector."""
        charge = self.ramp(illuminance_e, ngroups)
        return jnp.diff(self.read(charge), axis=0)

    @eqx.filter_jit
    def group_values(
        self, illuminance_e: Float[Array, "m m"], ngroups: int
    ) -> Float[Array, "g y x"]:
        """(ngroups, ny, nx) DN: the first group's read (the signal since the reset, no
        bias) and then the slopes of :meth:`slopes`: what a calslope file's values are
        with its first group in the likelihood (:mod:`amigo.model.detector.reset`)."""
        reads = self.read(self.ramp(illuminance_e, ngroups))
        return jnp.concatenate([reads[:1], jnp.diff(reads, axis=0)])


def _basis(grid: PupilGrid, centres: np.ndarray, radius: float, n: int) -> Array:
    """The Zernike basis, evaluated once as a constant of the pupil grid (op by op it
    takes seconds)."""
    with jax.ensure_compile_time_eval():
        return zernike_basis(grid, centres, radius, n)


@functools.lru_cache(maxsize=32)
def _filter_spectrum(filter_name: str, n_wavelengths: int, slope_per_um: float) -> LinearSpectrum:
    """Filter spectra are immutable and slow to build (the throughput curves are read
    from disk): build each once per process."""
    with jax.ensure_compile_time_eval():  # concrete arrays even when called under jit
        return LinearSpectrum.from_filter(filter_name, n_wavelengths, slope_per_um)


# ---------------------------------------------------------------------------- file I/O


def write_leaves(path: str | os.PathLike[str], tree: Any, record: dict[str, Any]) -> Path:
    """Write the array leaves of any pytree, keyed by path, plus a JSON record, to one
    ``.npz`` file (atomically). Used for base models and training checkpoints."""
    path = Path(path)
    # Any: numpy's stub types **kwds of savez_compressed as its allow_pickle flag too.
    arrays: dict[str, Any] = {name: np.asarray(leaf) for name, leaf in leaf_paths(tree).items()}
    arrays[METADATA_KEY] = np.array(json.dumps(record, indent=1, sort_keys=True))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:  # a file object: numpy would append ".npz" to a name
            np.savez_compressed(handle, **arrays)
    return path


def _is_array_or_shape(x: Any) -> bool:
    """An array leaf, or the shape of one (a skeleton from ``eqx.filter_eval_shape``)."""
    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def leaf_paths(tree: Any) -> dict[str, Array]:
    """``{path: array}`` for every array leaf of ``tree`` (paths as ``jax.tree_util.keystr``);
    a leaf that is only a shape (``jax.ShapeDtypeStruct``) counts as an array."""
    arrays = eqx.filter(tree, _is_array_or_shape)
    flat, _ = jax.tree_util.tree_flatten_with_path(arrays)
    return {jax.tree_util.keystr(path): leaf for path, leaf in flat}


def fill_leaves(
    path: Path,
    skeleton: Any,
    data: NpzFile,
    broadcast: tuple[str, ...] = (),
    from_skeleton: tuple[str, ...] = (),
    allow_infinite: bool = False,
) -> Any:
    """``skeleton`` with every array leaf replaced by the array stored under its path in
    ``data`` (an open npz); :class:`InputError` if paths or shapes differ. A 0-d array
    stored under a path in ``broadcast`` fills the leaf's whole shape, and the paths in
    ``from_skeleton`` keep the skeleton's value whether stored or not (older formats).
    NaN is refused always, infinities unless ``allow_infinite`` (a training checkpoint:
    the best loss before any network-on epoch, the Fisher information of pixels no
    calibrator sees)."""
    expected = leaf_paths(skeleton)
    stored = (set(data.files) - {METADATA_KEY}) | set(from_skeleton)
    if stored != set(expected):
        missing = sorted(set(expected) - stored)[:3]
        extra = sorted(stored - set(expected))[:3]
        raise InputError(path, f"parameters do not match: missing {missing}, unexpected {extra}")
    values = {}
    for name, leaf in expected.items():
        if name in from_skeleton:
            values[name] = np.asarray(leaf)
            continue
        array = data[name]
        if name in broadcast and array.shape == ():
            array = np.broadcast_to(array, leaf.shape)
        if array.shape != tuple(leaf.shape):
            raise InputError(path, f"{name} has shape {array.shape}, expected {leaf.shape}")
        if np.issubdtype(np.dtype(leaf.dtype), np.floating):
            if not np.issubdtype(array.dtype, np.floating):
                raise InputError(path, f"{name} has dtype {array.dtype}, expected floats")
            bad = np.isnan(array) if allow_infinite else ~np.isfinite(array)
            if np.any(bad):
                what = "NaN" if allow_infinite else "NaN or infinite"
                raise InputError(path, f"{name} holds {what} values")
        values[name] = array
    arrays, static = eqx.partition(skeleton, _is_array_or_shape)
    flat, treedef = jax.tree_util.tree_flatten_with_path(arrays)
    leaves = [jnp.asarray(values[jax.tree_util.keystr(p)]) for p, _ in flat]
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)


def save_base_model(
    model: BaseModel, path: str | os.PathLike[str], metadata: dict[str, Any] | None = None
) -> Path:
    """Write ``model`` (and a JSON provenance record) to one ``.npz`` file, atomically."""
    record = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": model.config.to_json(),
        "network": not model.linear,
        "dtype": str(np.asarray(model.hole_centres_m).dtype),
        **(metadata or {}),
    }
    migration = model.ramp.network
    if isinstance(migration, BoundaryShift):
        # The physical account in the network's place: its static shape, to rebuild the
        # skeleton (files without this record hold the network or nothing).
        record["boundary_shift"] = {
            "radius_pix": migration.radius_pix,
            "depth_pix": migration.depth_pix,
        }
    return write_leaves(path, model, record)


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON record of a base-model file (without loading the arrays)."""
    with open_npz(Path(path)) as data:
        return _metadata(Path(path), data)


def open_npz(path: Path, what: str = "base-model") -> NpzFile:
    """Open an ``.npz`` without pickle support; :class:`InputError` if impossible."""
    require_file(path, f"{what} file")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as error:  # zip and format errors come in several types
        raise InputError(path, f"not a {what} file ({error})") from None


def _metadata(path: Path, data, fmt: str = FORMAT) -> dict[str, Any]:
    if METADATA_KEY not in data.files:
        raise InputError(path, f"not a {fmt} file: no {METADATA_KEY} record")
    try:
        record = json.loads(str(data[METADATA_KEY]))
    except NPZ_DAMAGE as error:
        raise InputError(path, f"unreadable metadata ({error})") from None
    if not isinstance(record, dict):
        raise InputError(path, f"unreadable metadata (a {type(record).__name__}, not a record)")
    if record.get("format") != fmt:
        raise InputError(path, f"not a {fmt} file (format {record.get('format')!r})")
    version = record.get("format_version", 0)
    if not isinstance(version, int) or isinstance(version, bool) or version < 0:
        raise InputError(path, f"format_version is {version!r}, not a version number")
    if version > FORMAT_VERSION:
        raise InputError(
            path,
            f"{fmt} format version {record['format_version']} is newer than this "
            f"amigo understands ({FORMAT_VERSION}); upgrade amigo",
        )
    return record


def read_record(path: Path, data: NpzFile, fmt: str) -> dict[str, Any]:
    """The validated JSON record of an npz written by :func:`write_leaves`."""
    return _metadata(path, data, fmt)


def load_base_model(path: str | os.PathLike[str] | None = None) -> BaseModel:
    """Read a base model written by :func:`save_base_model` (default: the shipped one).

    Arrays keep the dtype they were stored in (float64 ones need 64-bit JAX enabled to
    stay float64). Raises :class:`InputError` when the file is not a base model or does
    not match the skeleton its config describes.
    """
    path = default_model_path() if path is None else Path(path)
    _verify_if_shipped(path)
    with open_npz(path) as data:
        try:
            return _load_base_model(path, data)
        except NPZ_DAMAGE as error:
            problem = f"{type(error).__name__}: {error}"
            raise InputError(path, f"damaged base-model file ({problem})") from None


def _load_base_model(path: Path, data) -> BaseModel:
    """The body of :func:`load_base_model` (``data``: the open archive)."""
    record = _metadata(path, data)
    config = BaseModelConfig.from_json(record.get("config", {}))
    skeleton = BaseModel.create(config, linear=True)
    shape = record.get("boundary_shift")
    if record.get("network", True) and shape is not None:
        if not isinstance(shape, dict):
            raise InputError(path, f"unreadable boundary_shift record {shape!r}")
        try:
            account = BoundaryShift.create(
                0.0, radius_pix=shape["radius_pix"], depth_pix=float(shape["depth_pix"])
            )
        except (KeyError, TypeError, ValueError, OverflowError) as error:
            raise InputError(
                path, f"unreadable boundary_shift record {shape!r} ({error})"
            ) from None
        skeleton = skeleton.with_network(account)
    elif record.get("network", True):
        # The network's shapes only: the stored weights replace them, and drawing
        # random ones would compile the random-number programs in every process.
        key = jax.ShapeDtypeStruct((2,), jnp.uint32)
        network = eqx.filter_eval_shape(
            ChargeMigrationNetwork,
            key,
            width=config.network_width,
            depth=config.network_depth,
            charge_scale_e=config.charge_scale_e,
        )
        skeleton = skeleton.with_network(network)
    # Files before format 2 hold one dark current for all pixels: spread it.
    version = int(record.get("format_version", 1))
    spread = (DARK_KEY,) if version < 2 else ()
    # Files before format 3 hold the detector rotation with the sign the research
    # code's resampler meant for coordinates (+0.561 deg: the image turned the wrong
    # way) and no skew or scale: they take the SIAF-derived geometry instead.
    geometry = GEOMETRY_KEYS if version < 3 else ()
    # Files before format 4 hold no hole sizes: the nominal ones.
    sizes = (HOLE_SIZES_KEY,) if version < 4 else ()
    return fill_leaves(path, skeleton, data, broadcast=spread, from_skeleton=(*geometry, *sizes))


#: The shipped models' SHA-256 digests (``sha256sum`` format), beside them in the package.
CHECKSUMS_NAME = "SHA256SUMS"


def verify_checksum(path: Path, sums: Path) -> None:
    """Raise :class:`InputError` when ``path`` is listed in the ``sums`` file (``sha256sum``
    output) with another digest: a shipped model damaged or altered after installation.
    Files the list does not name are not checked."""
    try:
        lines = sums.read_text(encoding="ascii").splitlines()
    except OSError:
        return  # an installation without the list: nothing to compare against
    pairs = (line.split(None, 1) for line in lines if line.strip())
    recorded = {name: digest for digest, name in pairs}
    expected = recorded.get(path.name)
    if expected is None:
        return
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != expected.strip():
        raise InputError(
            path,
            f"SHA-256 {digest[:12]}... differs from the {expected.strip()[:12]}... recorded in "
            f"{sums.name}: the shipped model is damaged; reinstall amigo",
        )


def _verify_if_shipped(path: Path) -> None:
    """:func:`verify_checksum` for the models in the package data."""
    folder = default_model_path().parent
    if path.resolve().parent == folder.resolve():
        verify_checksum(path, folder / CHECKSUMS_NAME)


def default_model_path() -> Path:
    """Path of the base model shipped in the package data (trained on the project's
    simulated raw ramps: the default for calslope files and the demo)."""
    resource = resources.files("amigo").joinpath(*DEFAULT_MODEL_RESOURCE)
    return Path(str(resource))


def level2_model_path() -> Path | None:
    """Path of the shipped base model trained on real level-2 calibrator images (the
    default for level-2 images), ``None`` if this installation has none."""
    path = Path(str(resources.files("amigo").joinpath(*LEVEL2_MODEL_RESOURCE)))
    return path if path.is_file() else None
