"""Physical truth model of the NIRISS H2RG detector for SUB80 ramps.

This is the simulator's *own* detector physics. It is deliberately independent of the
fitting model's detector (``amigo.model.detector``): the fitting model's neural network has to
learn the brighter-fatter effect from data made by different physics, so nothing here is
shared with it.

One integration is simulated in time, ``substeps_per_group`` sub-steps per group:

1. *Charge collection* (each sub-step): the oversampled photon rate, weighted by the
   intra-pixel response, is collected by pixels whose boundaries are shifted by the charge
   already collected (the brighter-fatter effect, :func:`boundary_shifts` and
   :func:`collect`); each pixel's collection efficiency is the flat field; photons
   arrive as Poisson draws; dark current adds Poisson charge; cosmic rays add charge at
   random times; charge is capped at the full well (saturation).
2. *Read-out* (at the end of each group): inter-pixel capacitance (a 5x5 convolution),
   per-pixel quadratic non-linearity, division by the gain, bias and per-integration
   reset offset, white read noise, 1/f noise correlated along the read (column stripes),
   the ADC's integral non-linearity (a sinusoid in raw counts) and quantisation to
   unsigned 16-bit counts.

Every effect has a switch in :class:`DetectorConfig`; docs/simulate.md lists them with
their defaults. Arrays are indexed ``[y, x]`` (rows, columns) in the DMS orientation of
SUB80 products; "up" is ``+y`` (increasing row index).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from amigo import niriss

#: Pixel pitch of the NIRISS H2RG (cm). Source: NIRISS detector overview (18 micron pixels).
PIXEL_PITCH_CM: float = 18.0e-4
#: Sample (pixel read) time (s). Source: TSAMPLE = 10 microseconds in AMI products.
SAMPLE_TIME_S: float = 10.0e-6
#: Largest raw count of the 16-bit ADC.
ADC_MAX_DN: int = 65535

#: Fraction of a cosmic ray's charge deposited in the 3x3 pixels around its hit (sums to 1).
COSMIC_RAY_FOOTPRINT: np.ndarray = np.array(
    [[0.015, 0.06, 0.015], [0.06, 0.70, 0.06], [0.015, 0.06, 0.015]]
)
COSMIC_RAY_FOOTPRINT.setflags(write=False)


def ipc_kernel() -> np.ndarray:
    """The 5x5 inter-pixel capacitance kernel, normalised to unit sum.

    ``kernel[2 + dy, 2 + dx]`` is the fraction of a pixel's signal seen in the pixel
    offset by ``(dx, dy)``. Values: centre 0.980177, left/right 4.710e-3, up (+y)
    3.980e-3, down (-y) 5.028e-3, diagonals 3.085e-4, corners -6.5e-6 (source: the
    CRDS-derived NIRISS kernel recorded in the AMIGO research notes); the rest of the
    outer ring is only known to lie between ~1e-5 and ~3e-5, and we set it to 3e-5 two
    pixels left/right, 2.5e-5 two pixels up/down and 1e-5 at the knight's moves. The raw
    values sum to 1.0000028; dividing by that sum makes IPC conserve charge.
    """
    k = np.zeros((5, 5))
    k[2, 2] = 0.980177
    k[2, 1] = k[2, 3] = 4.710e-3  # left / right
    k[3, 2] = 3.980e-3  # up (+y)
    k[1, 2] = 5.028e-3  # down (-y)
    k[1, 1] = k[1, 3] = k[3, 1] = k[3, 3] = 3.085e-4
    k[2, 0] = k[2, 4] = 3.0e-5
    k[0, 2] = k[4, 2] = 2.5e-5
    for dy, dx in ((-2, -1), (-2, 1), (2, -1), (2, 1), (-1, -2), (1, -2), (-1, 2), (1, 2)):
        k[2 + dy, 2 + dx] = 1.0e-5
    for dy in (-2, 2):
        for dx in (-2, 2):
            k[2 + dy, 2 + dx] = -6.5e-6
    return k / k.sum()


@dataclass(frozen=True)
class DetectorConfig:
    """Switches and parameters of the detector truth model (defaults: docs/simulate.md).

    Switches (``True`` = effect on): ``poisson`` (photon and dark shot noise; off uses
    expected values), ``flat_field``, ``intra_pixel``, ``bfe``, ``ipc``, ``nonlinearity``,
    ``dark_current``, ``bias``, ``reset_noise``, ``read_noise``, ``one_over_f``,
    ``cosmic_rays``, ``adc_inl``, ``saturation``, ``reference_pixels`` (the bottom
    :data:`amigo.niriss.N_REFERENCE_ROWS` rows of SUB80 collect no charge: bias and
    read noise only), ``quantize`` (round to integer counts and clip to 0..65535; off
    returns floating-point counts).

    Parameters are in the units their names say; ``bfe_strength_pix_per_e`` is the shift
    (pixels) of the boundary between two pixels per electron of charge difference
    between them (the nearest-neighbour coefficient ``a_00``).
    """

    poisson: bool = True
    flat_field: bool = True
    intra_pixel: bool = True
    bfe: bool = True
    ipc: bool = True
    nonlinearity: bool = True
    dark_current: bool = True
    bias: bool = True
    reset_noise: bool = True
    read_noise: bool = True
    one_over_f: bool = True
    cosmic_rays: bool = True
    adc_inl: bool = True
    saturation: bool = True
    reference_pixels: bool = True
    quantize: bool = True

    gain_e_per_dn: float = niriss.GAIN_E_PER_DN
    substeps_per_group: int = 4
    flat_rms: float = 0.02
    intra_pixel_edge_loss: float = 0.05
    bfe_strength_pix_per_e: float = 1.2e-6
    bfe_anisotropy: float = 1.0
    bfe_radius_pix: int = 2
    nonlinearity_c2_per_e: float = -6.0e-7
    nonlinearity_c2_rms_per_e: float = 5.0e-8
    dark_e_per_s: float = 0.45 / niriss.GROUP_TIME_S
    dark_log_scatter: float = 0.3
    bias_dn: float = 12000.0
    bias_rms_dn: float = 300.0
    reset_noise_dn: float = 12.0
    read_noise_dn: float = 6.6
    one_over_f_dn: float = 1.5
    cosmic_ray_rate_per_cm2_s: float = 5.0
    cosmic_ray_median_e: float = 1000.0
    cosmic_ray_log_scatter: float = 0.8
    adc_amplitude_dn: float = 2.0
    adc_period_dn: float = 1024.0
    full_well_e: float = 85000.0

    SWITCHES = (
        "poisson", "flat_field", "intra_pixel", "bfe", "ipc", "nonlinearity", "dark_current",
        "bias", "reset_noise", "read_noise", "one_over_f", "cosmic_rays", "adc_inl",
        "saturation", "reference_pixels", "quantize",
    )  # fmt: skip

    @classmethod
    def ideal(cls, **changes: Any) -> DetectorConfig:
        """Every effect off (a linear, noiseless, float-valued detector), then ``changes``."""
        off = {name: False for name in cls.SWITCHES}
        off.update(changes)
        return cls(**off)

    @classmethod
    def noiseless(cls, **changes: Any) -> DetectorConfig:
        """All deterministic physics on, every random effect and quantisation off."""
        values: dict[str, Any] = {
            "poisson": False, "reset_noise": False, "read_noise": False,
            "one_over_f": False, "cosmic_rays": False, "quantize": False,
        }  # fmt: skip
        values.update(changes)
        return cls(**values)

    def replace(self, **changes: Any) -> DetectorConfig:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_mapping(
        cls, values: dict[str, Any], base: DetectorConfig | None = None
    ) -> DetectorConfig:
        """Apply a TOML ``[detector]`` table to ``base`` (``ValueError`` on unknown keys)."""
        base = base or cls()
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ValueError(f"unknown [detector] keys {unknown}; known: {sorted(fields)}")
        typed: dict[str, Any] = {}
        for key, value in values.items():
            current = getattr(base, key)
            if isinstance(current, bool):
                if not isinstance(value, bool):
                    raise ValueError(f"[detector] {key} must be true or false")
                typed[key] = value
            elif isinstance(current, int):
                typed[key] = int(value)
            else:
                typed[key] = float(value)
        config = dataclasses.replace(base, **typed)
        config.check()
        return config

    def check(self) -> None:
        """Raise ``ValueError`` for parameters outside their physical range."""
        if self.substeps_per_group < 1:
            raise ValueError("substeps_per_group must be >= 1")
        if self.gain_e_per_dn <= 0 or self.full_well_e <= 0 or self.adc_period_dn <= 0:
            raise ValueError("gain, full well and ADC period must be positive")
        if not 0 <= self.intra_pixel_edge_loss < 1:
            raise ValueError("intra_pixel_edge_loss must lie in [0, 1)")
        if self.bfe_radius_pix < 1:
            raise ValueError("bfe_radius_pix must be >= 1")
        for name in ("flat_rms", "read_noise_dn", "reset_noise_dn", "one_over_f_dn",
                     "bias_rms_dn", "dark_e_per_s", "cosmic_ray_rate_per_cm2_s",
                     "bfe_strength_pix_per_e"):  # fmt: skip
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")

    def to_json(self) -> dict[str, Any]:
        """All switches and parameters (JSON-ready)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


# --------------------------------------------------------------------------------------
# Per-pixel properties: drawn once per detector
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectorRealisation:
    """The per-pixel truth of one detector (drawn once per scenario), each (80, 80).

    Attributes
    ----------
    flat
        Collection efficiency of each pixel (mean ~1).
    nonlinearity_c2_per_e
        Quadratic non-linearity: measured = q (1 + c2 q), q in electrons.
    bias_dn
        Bias level (DN).
    dark_e_per_s
        Dark current (electrons/s).
    """

    flat: np.ndarray
    nonlinearity_c2_per_e: np.ndarray
    bias_dn: np.ndarray
    dark_e_per_s: np.ndarray

    def to_json(self) -> dict[str, Any]:
        """Per-pixel maps as nested lists (rounded to float32 precision)."""
        return {
            name: np.asarray(getattr(self, name), np.float32).tolist()
            for name in ("flat", "nonlinearity_c2_per_e", "bias_dn", "dark_e_per_s")
        }


def draw_detector(
    rng: np.random.Generator, config: DetectorConfig, shape: tuple[int, int] | None = None
) -> DetectorRealisation:
    """Draw the per-pixel truth. All maps are drawn whatever the switches (fixed order),
    so turning one effect off never changes the others."""
    shape = shape or (niriss.SUBARRAY_SIZE, niriss.SUBARRAY_SIZE)
    flat = 1.0 + config.flat_rms * rng.standard_normal(shape)
    c2 = config.nonlinearity_c2_per_e + config.nonlinearity_c2_rms_per_e * rng.standard_normal(
        shape
    )
    bias = config.bias_dn + config.bias_rms_dn * rng.standard_normal(shape)
    # Log-normal scatter with the configured mean.
    log_dark = config.dark_log_scatter * rng.standard_normal(shape)
    dark = config.dark_e_per_s * np.exp(log_dark - 0.5 * config.dark_log_scatter**2)
    return DetectorRealisation(flat=flat, nonlinearity_c2_per_e=c2, bias_dn=bias, dark_e_per_s=dark)


def intra_pixel_response(oversample: int, edge_loss: float) -> np.ndarray:
    """(k, k) relative response of the sub-pixels of a pixel, mean exactly 1.

    A quadratic bowl ``1 - c (u^2 + v^2)`` over the pixel (``u, v`` in -1/2..1/2 at the
    sub-pixel centres), with ``c`` such that the response at the middle of an edge is
    ``1 - edge_loss`` times the response at the centre.
    """
    k = int(oversample)
    u = (np.arange(k) + 0.5) / k - 0.5
    bowl = 1.0 - 4.0 * edge_loss * (u[:, None] ** 2 + u[None, :] ** 2)
    return bowl / bowl.mean()


# --------------------------------------------------------------------------------------
# The brighter-fatter effect: pixel-boundary shifts
# --------------------------------------------------------------------------------------


def bfe_coefficients(strength_pix_per_e: float, radius_pix: int) -> np.ndarray:
    """Coefficients ``a[R + n, m]`` of the boundary-shift model, shape (2R+1, R).

    The boundary between a pixel and its neighbour along the boundary's normal moves by
    ``a[R + n, m]`` pixels per electron of charge *difference* between the two pixels
    that sit ``m`` pixels beyond either side of the boundary and ``n`` pixels along it
    (``m = 0``: the two pixels sharing the boundary). The shape is that of the normal
    component of a point charge's field at the boundary's midpoint,
    ``(m + 1/2) / ((m + 1/2)^2 + n^2)^(3/2)``, scaled so that ``a[R, 0]`` equals
    ``strength_pix_per_e``.
    """
    radius = int(radius_pix)
    n = np.arange(-radius, radius + 1)[:, None]
    m = np.arange(radius)[None, :] + 0.5
    shape = m / (m**2 + n**2) ** 1.5
    return strength_pix_per_e * shape / shape[radius, 0]


def boundary_shifts(
    charge_e: np.ndarray, coeff_x: np.ndarray, coeff_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Displacements of the pixel boundaries caused by the collected charge.

    Parameters
    ----------
    charge_e
        (ny, nx) charge in each pixel (electrons). Charge outside the array counts as 0.
    coeff_x, coeff_y
        (2R+1, R) coefficients (:func:`bfe_coefficients`) for the boundaries between
        horizontal neighbours (normal along x) and vertical neighbours (normal along y).

    Returns
    -------
    shift_x
        (ny, nx-1): displacement (pixels, ``+x`` positive) of the boundary between pixel
        ``[y, x]`` and ``[y, x+1]``. Charge on the ``+x`` side pushes it towards ``+x``
        (the charged pixel repels arriving electrons and so shrinks), charge on the
        ``-x`` side towards ``-x``.
    shift_y
        (ny-1, nx): the same for the boundary between ``[y, x]`` and ``[y+1, x]``.
    """
    ny, nx = charge_e.shape
    radius = coeff_x.shape[1]
    padded = np.pad(charge_e, radius)
    shift_x = np.zeros((ny, nx - 1))
    shift_y = np.zeros((ny - 1, nx))
    r = radius
    for i, n in enumerate(range(-r, r + 1)):
        for m in range(r):
            ax, ay = coeff_x[i, m], coeff_y[i, m]
            # x-boundaries between columns x and x+1 (x = 0..nx-2), rows shifted by n.
            rows = slice(r + n, r + n + ny)
            plus = padded[rows, r + 1 + m : r + 1 + m + nx - 1]
            minus = padded[rows, r - m : r - m + nx - 1]
            shift_x += ax * (plus - minus)
            # y-boundaries between rows y and y+1, columns shifted by n.
            cols = slice(r + n, r + n + nx)
            plus = padded[r + 1 + m : r + 1 + m + ny - 1, cols]
            minus = padded[r - m : r - m + ny - 1, cols]
            shift_y += ay * (plus - minus)
    return shift_x, shift_y


@dataclass(frozen=True)
class EdgeStrips:
    """The oversampled photon rate summarised for the boundary-shift model.

    For every boundary, the rate (photons/s) falling in each sub-pixel strip parallel to
    it, counted from the boundary into either pixel. With the boundary displaced by
    ``s`` pixels, the strips it sweeps over (the first ``floor(|s| k)`` entirely, the next
    partly, with the rate uniform inside a sub-pixel) change owner.

    Attributes
    ----------
    total
        (ny, nx) rate collected by each pixel with undisplaced boundaries.
    minus_x, plus_x
        (k, ny, nx-1): ``minus_x[j]`` is the rate in the ``j``-th sub-column left of the
        boundary between ``[y, x]`` and ``[y, x+1]`` (inside ``[y, x]``), ``plus_x[j]`` the
        ``j``-th right of it (inside ``[y, x+1]``).
    minus_y, plus_y
        (k, ny-1, nx): the same for the boundary between ``[y, x]`` and ``[y+1, x]``.
    """

    total: np.ndarray
    minus_x: np.ndarray
    plus_x: np.ndarray
    minus_y: np.ndarray
    plus_y: np.ndarray

    @property
    def oversample(self) -> int:
        return self.minus_x.shape[0]

    @classmethod
    def from_rate(cls, rate_sub: np.ndarray, oversample: int) -> EdgeStrips:
        """Build from an oversampled rate image of shape (ny k, nx k)."""
        k = int(oversample)
        ny, nx = rate_sub.shape[0] // k, rate_sub.shape[1] // k
        blocks = rate_sub.reshape(ny, k, nx, k)
        columns = blocks.sum(axis=1)  # (ny, nx, k): sub-columns of each pixel
        rows = blocks.sum(axis=3)  # (ny, k, nx): sub-rows of each pixel
        minus_x = np.stack([columns[:, :-1, k - 1 - j] for j in range(k)])
        plus_x = np.stack([columns[:, 1:, j] for j in range(k)])
        minus_y = np.stack([rows[:-1, k - 1 - j, :] for j in range(k)])
        plus_y = np.stack([rows[1:, j, :] for j in range(k)])
        return cls(blocks.sum(axis=(1, 3)), minus_x, plus_x, minus_y, plus_y)


def _swept(strips_minus: np.ndarray, strips_plus: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Net rate crossing each boundary from its minus to its plus side, given its shift.

    A boundary moving towards minus (``shift < 0``) hands the minus pixel's swept strips
    to the plus pixel, and vice versa.
    """
    k = strips_minus.shape[0]
    depth = np.abs(shift) * k  # swept depth in sub-pixels
    n_strips = min(int(np.ceil(depth.max())) if depth.size else 0, k)
    moved_minus = np.zeros_like(shift)
    moved_plus = np.zeros_like(shift)
    for j in range(n_strips):
        fraction = np.clip(depth - j, 0.0, 1.0)
        moved_minus += fraction * strips_minus[j]
        moved_plus += fraction * strips_plus[j]
    return np.where(shift < 0, moved_minus, -moved_plus)


def collect(strips: EdgeStrips, shift_x: np.ndarray, shift_y: np.ndarray) -> np.ndarray:
    """Photon rate collected by each pixel with displaced boundaries (photons/s).

    Flux-conserving by construction: whatever one pixel loses across a boundary, its
    neighbour gains, so ``collect(...).sum() == strips.total.sum()`` up to rounding.
    Shifts are capped at one pixel (far beyond any physical value).
    """
    shift_x = np.clip(shift_x, -1.0, 1.0)
    shift_y = np.clip(shift_y, -1.0, 1.0)
    flow_x = _swept(strips.minus_x, strips.plus_x, shift_x)  # (ny, nx-1), minus -> plus
    flow_y = _swept(strips.minus_y, strips.plus_y, shift_y)  # (ny-1, nx)
    rate = strips.total.copy()
    rate[:, :-1] -= flow_x
    rate[:, 1:] += flow_x
    rate[:-1, :] -= flow_y
    rate[1:, :] += flow_y
    return rate


# --------------------------------------------------------------------------------------
# Read-out
# --------------------------------------------------------------------------------------


def convolve_ipc(charge: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Apply IPC: ``out[p + d] += kernel[d] * charge[p]`` (zero signal beyond the edges)."""
    ny, nx = charge.shape
    half = kernel.shape[0] // 2
    padded = np.zeros((ny + 2 * half, nx + 2 * half))
    for iy in range(kernel.shape[0]):
        for ix in range(kernel.shape[1]):
            weight = kernel[iy, ix]
            if weight != 0.0:
                padded[iy : iy + ny, ix : ix + nx] += weight * charge
    return padded[half : half + ny, half : half + nx]


def adc_transfer(analog_dn: np.ndarray, amplitude_dn: float, period_dn: float) -> np.ndarray:
    """Integral non-linearity of the ADC: ``raw = v + A sin(2 pi v / P)`` (before rounding)."""
    return analog_dn + amplitude_dn * np.sin(2.0 * np.pi * analog_dn / period_dn)


def one_over_f_columns(
    rng: np.random.Generator,
    ngroups: int,
    nx: int,
    ny: int,
    rms_dn: float,
    frame_time_s: float = niriss.FRAME_TIME_S,
) -> np.ndarray:
    """1/f noise of the read-out amplifier as a per-group column offset, (ngroups, nx).

    The amplifier drifts with a 1/f power spectrum in time. SUB80 is read column by
    column along the fast axis (``FASTAXIS = -2``, ``SLOWAXIS = -1``), one column in
    ``ny * SAMPLE_TIME_S`` (0.8 ms), so the drift is nearly constant along a column and
    different from column to column and group to group: vertical stripes. The series
    covers the whole integration (with the frame's idle time as extra slots), so its
    lowest frequency is one per integration. ``rms_dn`` is the expected RMS per slot.
    """
    column_time = ny * SAMPLE_TIME_S
    slots_per_frame = max(nx, round(frame_time_s / column_time))
    length = ngroups * slots_per_frame
    freq = np.fft.rfftfreq(length)
    filt = np.zeros_like(freq)
    filt[1:] = 1.0 / np.sqrt(freq[1:])
    # Variance of irfft(rfft(white) * filt) for unit white noise: mean of |filt|^2 over
    # the full (Hermitian) spectrum.
    weights = np.full(freq.size, 2.0)
    weights[0] = 1.0
    if length % 2 == 0:
        weights[-1] = 1.0
    variance = np.sum(weights * filt**2) / length
    if variance == 0:
        return np.zeros((ngroups, nx))
    series = np.fft.irfft(np.fft.rfft(rng.standard_normal(length)) * filt, n=length)
    series *= rms_dn / np.sqrt(variance)
    frames = series.reshape(ngroups, slots_per_frame)
    # Columns are read from the last to the first (SLOWAXIS = -1).
    return frames[:, :nx][:, ::-1]


# --------------------------------------------------------------------------------------
# One integration
# --------------------------------------------------------------------------------------


@dataclass
class IntegrationTruth:
    """What happened during one integration (for the truth file)."""

    photons: float
    dark_e: float
    cosmic_rays: list[dict[str, float]]
    saturated_pixels: int


class RampSimulator:
    """Simulates integrations of one exposure (fixed illumination and detector).

    Parameters
    ----------
    rate_sub
        (80 k, 80 k) photon rate on the oversampled grid (photons/s per sub-pixel).
    oversample
        ``k``.
    realisation
        Per-pixel truth of the detector.
    config
        Switches and parameters.
    ngroups
        Groups per integration.
    group_time_s
        Time between group reads (NISRAPID: one frame per group, no gaps).
    """

    def __init__(
        self,
        rate_sub: np.ndarray,
        oversample: int,
        realisation: DetectorRealisation,
        config: DetectorConfig,
        ngroups: int,
        group_time_s: float = niriss.GROUP_TIME_S,
    ) -> None:
        config.check()
        k = int(oversample)
        if rate_sub.shape[0] % k or rate_sub.shape[1] % k:
            raise ValueError(f"rate image {rate_sub.shape} is not a multiple of oversample {k}")
        if ngroups < 1:
            raise ValueError("ngroups must be >= 1")
        self.config = config
        self.realisation = realisation
        self.ngroups = int(ngroups)
        self.group_time_s = float(group_time_s)
        self.oversample = k
        rate = np.asarray(rate_sub, float)
        if config.intra_pixel:
            response = intra_pixel_response(k, config.intra_pixel_edge_loss)
            rate = rate * np.tile(response, (rate.shape[0] // k, rate.shape[1] // k))
        self.strips = EdgeStrips.from_rate(rate, k)
        self.shape = self.strips.total.shape
        strength = config.bfe_strength_pix_per_e
        self.coeff_x = bfe_coefficients(strength, config.bfe_radius_pix)
        self.coeff_y = bfe_coefficients(strength * config.bfe_anisotropy, config.bfe_radius_pix)
        self.efficiency = realisation.flat if config.flat_field else np.ones(self.shape)
        # Reference pixels have no photodiode: no photo-charge, dark current or cosmic rays.
        self.active = np.ones(self.shape)
        if config.reference_pixels and self.shape[0] > niriss.N_REFERENCE_ROWS:
            self.active[: niriss.N_REFERENCE_ROWS] = 0.0
        self.ipc = ipc_kernel()

    # ---------------------------------------------------------------- physics pieces
    def collected_rate(self, charge_e: np.ndarray) -> np.ndarray:
        """Mean photo-electron rate (e-/s) per pixel given the charge already collected."""
        if self.config.bfe:
            shift_x, shift_y = boundary_shifts(charge_e, self.coeff_x, self.coeff_y)
            rate = collect(self.strips, shift_x, shift_y)
        else:
            rate = self.strips.total
        return self.efficiency * rate

    def read(self, charge_e: np.ndarray, offset_dn: np.ndarray) -> np.ndarray:
        """Raw counts for the charge in each pixel (before quantisation), DN.

        ``offset_dn`` holds the additive terms of this read (bias, reset offset, read
        noise, 1/f) that do not depend on the charge.
        """
        cfg = self.config
        signal = convolve_ipc(charge_e, self.ipc) if cfg.ipc else charge_e
        if cfg.nonlinearity:
            signal = signal * (1.0 + self.realisation.nonlinearity_c2_per_e * signal)
        analog = signal / cfg.gain_e_per_dn + offset_dn
        if cfg.adc_inl:
            analog = adc_transfer(analog, cfg.adc_amplitude_dn, cfg.adc_period_dn)
        return analog

    def _cosmic_rays(self, rng: np.random.Generator) -> list[tuple[int, int, int, float]]:
        """Cosmic ray hits of one integration: (sub-step, y, x, electrons), time-ordered."""
        cfg = self.config
        ny, nx = self.shape
        n_steps = self.ngroups * cfg.substeps_per_group
        duration = self.ngroups * self.group_time_s
        area_cm2 = ny * nx * PIXEL_PITCH_CM**2
        count = rng.poisson(cfg.cosmic_ray_rate_per_cm2_s * area_cm2 * duration)
        times = np.sort(rng.uniform(0.0, duration, count))
        ys = rng.integers(0, ny, count)
        xs = rng.integers(0, nx, count)
        energy = cfg.cosmic_ray_median_e * np.exp(
            cfg.cosmic_ray_log_scatter * rng.standard_normal(count)
        )
        steps = np.minimum((times / duration * n_steps).astype(int), n_steps - 1)
        return [
            (int(s), int(y), int(x), float(e))
            for s, y, x, e in zip(steps, ys, xs, energy, strict=True)
        ]

    # ---------------------------------------------------------------- the ramp
    def integration(self, rng: np.random.Generator) -> tuple[np.ndarray, IntegrationTruth]:
        """Simulate one integration.

        Returns
        -------
        ramp
            (ngroups, ny, nx) raw counts: ``uint16`` when ``quantize`` is on, else float64.
        truth
            Photons collected, dark charge, cosmic rays, saturated pixel count.
        """
        cfg = self.config
        ny, nx = self.shape
        nsub = cfg.substeps_per_group
        dt = self.group_time_s / nsub
        # Random draws of the read chain come first, in a fixed order, so that switching
        # a collection effect does not reshuffle the noise of the reads.
        offsets = np.zeros((self.ngroups, ny, nx))
        if cfg.bias:
            offsets += self.realisation.bias_dn
        if cfg.reset_noise:
            offsets += cfg.reset_noise_dn * rng.standard_normal((ny, nx))
        if cfg.read_noise:
            offsets += cfg.read_noise_dn * rng.standard_normal((self.ngroups, ny, nx))
        if cfg.one_over_f:
            columns = one_over_f_columns(rng, self.ngroups, nx, ny, cfg.one_over_f_dn)
            offsets += columns[:, None, :]
        hits = self._cosmic_rays(rng) if cfg.cosmic_rays else []

        charge = np.zeros((ny, nx))
        dark_rate = self.realisation.dark_e_per_s if cfg.dark_current else np.zeros((ny, nx))
        ramp = np.empty((self.ngroups, ny, nx))
        photons = 0.0
        dark_total = 0.0
        recorded: list[dict[str, float]] = []
        hit_index = 0
        step = 0
        padded = np.zeros((ny + 2, nx + 2))
        for group in range(self.ngroups):
            for _ in range(nsub):
                mean = self.collected_rate(charge) * dt
                if cfg.poisson:
                    photo = rng.poisson(mean).astype(float)
                    dark = rng.poisson(dark_rate * dt).astype(float)
                else:
                    photo = mean
                    dark = dark_rate * dt
                photo = photo * self.active
                dark = dark * self.active
                photons += float(photo.sum())
                dark_total += float(dark.sum())
                charge += photo + dark
                while hit_index < len(hits) and hits[hit_index][0] == step:
                    _, y, x, energy = hits[hit_index]
                    padded[:] = 0.0
                    padded[y : y + 3, x : x + 3] = energy * COSMIC_RAY_FOOTPRINT
                    charge += padded[1:-1, 1:-1] * self.active
                    recorded.append({"group": group, "y": y, "x": x, "electrons": energy})
                    hit_index += 1
                if cfg.saturation:
                    np.minimum(charge, cfg.full_well_e, out=charge)
                step += 1
            ramp[group] = self.read(charge, offsets[group])
        saturated = int(np.sum(charge >= cfg.full_well_e)) if cfg.saturation else 0
        if cfg.quantize:
            ramp = np.clip(np.rint(ramp), 0, ADC_MAX_DN).astype(np.uint16)
        return ramp, IntegrationTruth(photons, dark_total, recorded, saturated)
