"""One abstraction for every kind of interferometric observable amigo fits.

A data *block* (one file, one filter) is described by a chain of maps from the complex
visibility ``V`` at ``n_uv`` uv points to ``n_obs`` statistically independent observables::

    L    = [log|V|, arg V]                              (2 n_uv,)   log visibility
    raw  = g(A @ L)                                     (n_raw,)    e.g. V2, closure phases
    z    = P @ wrap(raw - raw_data) / error             (n_obs,)    whitened residuals

* calvis files (DISCOs): ``A`` is the file's DISCO matrix, ``g`` the identity, ``P`` the
  identity: the observables are already independent.
* OIFITS: ``raw`` holds V2 (``g = exp`` of twice the log-amplitude) and closure phases
  (``A`` is the closure operator on the phases, ``g`` the identity, residuals wrapped into
  (-pi, pi]); ``P`` rotates correlated observables into the eigenbasis of their covariance
  (``error`` = square roots of its eigenvalues), so that ``z`` is independent in all cases.

The closure phases of a 7-hole mask are not independent (35 triangles, 15 independent
combinations). When a file gives no covariance, amigo by default assumes the closure
phases come from independent baseline-phase noise (each triangle sharing a baseline with
another is correlated by +-1/3) and keeps the 15 independent combinations; treating the 35
as independent would overstate every significance by about sqrt(7/3) = 1.5.

``uv_m`` is stored already rotated onto the sky (see :mod:`amigo.companions.models`): for
calvis files ``b_sky = S^T b`` with ``S`` the file's sky-to-uv matrix, so that
``b . (S theta_sky) = b_sky . theta_sky``; OIFITS u, v are on the sky by definition.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import os
import threading
import weakref
from collections.abc import Sequence
from typing import Any, Literal, TypeVar, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from amigo import programs
from amigo.companions.models import scene_visibility
from amigo.errors import InputError
from amigo.io.calvis import CalVis, is_calvis, read_calvis
from amigo.io.files import require_file
from amigo.io.jwst import open_fits
from amigo.io.oifits import OIFits, is_oifits, read_oifits

#: Observable kinds, indexed by the integers stored in :attr:`Observables.kinds`.
KIND_NAMES: tuple[str, ...] = ("amplitude", "phase")
AMPLITUDE, PHASE = 0, 1

#: Number of wavelengths that sample an OIFITS channel's bandwidth (a top hat).
OIFITS_BAND_SAMPLES = 5

#: Eigenvalues below this fraction of the largest are the null space of a covariance.
COVARIANCE_RANK_TOL = 1e-9

#: uv points of a calvis file left out when read: the largest set of its weakest points
#: whose whitened DISCO-matrix columns (``A / error``, both halves) have a Frobenius norm
#: of at most this. See :func:`silent_uv_points` for what that bounds.
SILENT_UV_TOLERANCE = 0.01

#: Fraction of a calvis file's information within its longest baseline ``B_max``
#: (:func:`information_radius_m`).
INFORMATION_FRACTION = 0.99

#: An array leaf of :class:`Observables`: NumPy as built, a JAX array where traced.
Leaf = np.ndarray | Array
#: A 2x2 matrix as nested tuples (hashable: static metadata).
Matrix2 = tuple[tuple[float, float], tuple[float, float]]

T = TypeVar("T")


class Observables(eqx.Module):
    """Independent observables of one target in one filter, and how to predict them.

    Array attributes (shapes in brackets) are pytree leaves, stored as NumPy float64 so
    that the precision is decided where they are used (amigo runs its fits in float64
    contexts); the rest is static metadata.

    Attributes
    ----------
    uv_m
        [n_uv, 2] uv points (m) in the sky-aligned frame (x east, y north).
    wavelengths_m, weights
        [n_uv, n_wl] wavelengths (m) and normalised weights at each uv point.
    design_head, design_tail
        The linear map ``A`` (:attr:`design`, [n_raw, 2 n_uv]) from ``[log|V|, arg V]`` to
        raw observables, stored in two parts: [n_head, n_uv] for its leading rows that do
        not depend on ``arg V`` (a calvis file's DISCO amplitudes, an OIFITS file's V2),
        without their zero half, and [n_raw - n_head, 2 n_uv] for the rest. A quarter of
        a calvis matrix is those zeros, and its products (NUTS, the grid) are bound by
        reading it.
    exp_rows, wrap_rows
        [n_raw] booleans: raw observables that are ``exp`` of their linear part (V2), and
        those whose residuals are angles to wrap (closure phases).
    data_raw
        [n_raw] measured raw observables.
    projection
        [n_obs, n_raw] whitening rotation ``P`` (identity for calvis files).
    errors
        [n_obs] 1-sigma errors of the independent observables.
    kinds
        (n_obs ints, static) 0 for amplitude-like, 1 for phase-like observables.
    filter_name, source, target
        Filter, input file, target name.
    n_photons
        Photons behind the observables (NaN if unknown); ``photon_source`` says where the
        number came from (``"NPHOT"`` or ``"closure-phase errors"``).
    linear
        True when the observables are linear in the log visibility (no ``exp`` rows, no
        wrapping, no projection: calvis files); the grid search then uses a faster path.
    """

    uv_m: Leaf
    wavelengths_m: Leaf
    weights: Leaf
    design_head: Leaf
    design_tail: Leaf
    exp_rows: Leaf
    wrap_rows: Leaf
    data_raw: Leaf
    projection: Leaf | None
    errors: Leaf
    kinds: tuple[int, ...] = eqx.field(static=True)
    filter_name: str = eqx.field(static=True)
    source: str = eqx.field(static=True)
    target: str = eqx.field(static=True, default="")
    n_photons: float = eqx.field(static=True, default=float("nan"))
    photon_source: str = eqx.field(static=True, default="")
    linear: bool = eqx.field(static=True, default=False)
    sky_to_uv: Matrix2 = eqx.field(static=True, default=((1.0, 0.0), (0.0, 1.0)))
    #: Longest baseline (m) the observables see, fixed when the file is read (the inner
    #: working angle and the grid's step are the file's, whatever amigo evaluates): for
    #: a calvis file its :func:`information_radius_m`, not its grid's corner.
    longest_baseline_m: float = eqx.field(static=True, default=float("nan"))

    # ------------------------------------------------------------------ sizes
    @property
    def n_obs(self) -> int:
        return int(self.errors.shape[0])

    @property
    def n_uv(self) -> int:
        return int(self.uv_m.shape[0])

    @property
    def max_baseline_m(self) -> float:
        if np.isfinite(self.longest_baseline_m):
            return self.longest_baseline_m
        return float(np.max(np.hypot(self.uv_m[:, 0], self.uv_m[:, 1])))

    @property
    def mean_wavelength_m(self) -> float:
        return float(np.sum(self.wavelengths_m * self.weights) / np.sum(self.weights))

    @property
    def min_wavelength_m(self) -> float:
        return float(np.min(np.where(self.weights > 0, self.wavelengths_m, np.inf)))

    @property
    def design(self) -> np.ndarray:
        """[n_raw, 2 n_uv] the whole linear map ``A`` (NumPy; the model uses its parts)."""
        head = np.asarray(self.design_head)
        head = np.concatenate([head, np.zeros_like(head)], axis=1)
        return np.concatenate([head, np.asarray(self.design_tail)], axis=0)

    # ------------------------------------------------------------------ model
    def linear_part(self, log_vis: Array) -> Array:
        """``A [log|V|, arg V]``: (..., n_raw) for ``log_vis`` (..., 2 n_uv)."""
        n_uv = self.uv_m.shape[0]
        # Contract with the matrices' second axis as they are stored: written as
        # ``log_vis @ design.T``, XLA may copy each transposed matrix first.
        last = log_vis.ndim - 1
        head = jnp.tensordot(log_vis[..., :n_uv], self.design_head, axes=((last,), (1,)))
        tail = jnp.tensordot(log_vis, self.design_tail, axes=((last,), (1,)))
        return jnp.concatenate([head, tail], axis=-1)

    def raw(self, vis: Array) -> Array:
        """Raw observables (n_raw,) of a complex visibility (n_uv,) (principal-branch log).

        The phase of ``log V`` is continuous as long as the companions' total flux ratio is
        below the primary's visibility at every uv point (always for an unresolved primary
        and a total flux ratio below one): then ``Re V > 0`` and no branch cut is crossed.
        """
        log_vis = jnp.concatenate([jnp.log(jnp.abs(vis)), jnp.angle(vis)])
        linear = self.linear_part(log_vis)
        return jnp.where(self.exp_rows, jnp.exp(linear), linear)

    def _whiten(self, raw_residual: Array) -> Array:
        wrapped = jnp.where(self.wrap_rows, jnp.angle(jnp.exp(1j * raw_residual)), raw_residual)
        # NumPy @ JAX array is a JAX array (JAX's __rmatmul__), which typeshed cannot see.
        return wrapped if self.projection is None else cast(Array, self.projection @ wrapped)

    def residuals(self, vis: Array) -> Array:
        """Whitened residuals ``(model - data) / error`` (n_obs,) for a visibility (n_uv,)."""
        return self._whiten(self.raw(vis) - self.data_raw) / self.errors

    def observed(self) -> Leaf:
        """The independent observables (data)."""
        return self.data_raw if self.projection is None else self.projection @ self.data_raw

    def predicted(self, vis: Array) -> Leaf:
        """Model independent observables (data + wrapped difference, for plots)."""
        return self.observed() + self._whiten(self.raw(vis) - self.data_raw)


@programs.jit
def predicted_scenes(
    block: Observables, offsets_mas: Array, contrasts: Array, diameter_mas: float
) -> Array:
    """(n, n_obs) :meth:`Observables.predicted` for ``n`` scenes of a primary of
    ``diameter_mas`` and companions at ``offsets_mas`` (n, n_comp, 2) with flux ratios
    ``contrasts`` (n, n_comp): one compiled program (the posterior predictive figure's 50
    draws took ~2 s op by op)."""

    def one(offsets, flux_ratios):
        vis = scene_visibility(
            block.uv_m, block.wavelengths_m, block.weights, offsets, flux_ratios, diameter_mas
        )
        return block.predicted(vis)

    return jax.vmap(one)(offsets_mas, contrasts)


# ---------------------------------------------------------------------------- builders
def _split_design(design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``design`` [n_raw, 2 n_uv] as :class:`Observables`' two parts ``(design_head,
    design_tail)``: the leading rows whose ``arg V`` half is zero (without it), and the
    rest."""
    design = np.asarray(design)
    n_uv = design.shape[1] // 2
    free = np.all(design[:, n_uv:] == 0.0, axis=1)
    n_head = len(free) if free.all() else int(np.argmin(free))
    return design[:n_head, :n_uv].copy(), design[n_head:].copy()


def silent_uv_points(design: np.ndarray, errors: np.ndarray, tolerance: float) -> np.ndarray:
    """(n_uv,) True for the uv points of a linear map that observables barely see.

    ``design`` [n_obs, 2 n_uv] maps ``L = [log|V|, arg V]`` to observables with
    ``errors`` [n_obs]. The points chosen are the largest set ``D`` of the weakest ones
    (by the norm of their two whitened columns) whose whitened columns ``A_D`` have a
    Frobenius norm of at most ``tolerance``. Leaving them out changes the whitened
    residuals of any scene by ``A_D L_D``, at most ``tolerance * |L_D|`` in norm, and so
    (to first order) moves any fitted parameter by at most that many of its standard
    errors: for companions of flux ratio ``c``, ``|L_D| <~ c sqrt(2 |D|)``.

    A calvis file's matrix spans the whole knot grid of the latent visibilities, knots
    beyond the mask's transfer function included: on the AB Dor files 13-39 % of the
    knots have, together, whitened columns of norm 0.01, where one knot inside a splodge
    has 1.4-3.8 (the median). They cost the companion models as much as any other point
    and tell them nothing.
    """
    power = _point_power(design, errors)
    n_uv = power.size
    order = np.argsort(power, kind="stable")
    n_silent = int(np.searchsorted(np.cumsum(power[order]), tolerance**2, side="right"))
    silent = np.zeros(n_uv, dtype=bool)
    silent[order[: min(n_silent, n_uv - 1)]] = True  # a block keeps at least one point
    return silent


def _point_power(design: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """(n_uv,) each uv point's whitened information: the squared norm of its two columns
    (log-amplitude and phase) of ``design / errors`` ([n_obs, 2 n_uv], [n_obs])."""
    whitened = np.asarray(design, dtype=float) / np.asarray(errors, dtype=float)[:, None]
    n_uv = whitened.shape[1] // 2
    return np.sum(whitened[:, :n_uv] ** 2, axis=0) + np.sum(whitened[:, n_uv:] ** 2, axis=0)


def information_radius_m(
    uv_m: np.ndarray, design: np.ndarray, errors: np.ndarray, fraction: float = INFORMATION_FRACTION
) -> float:
    """The baseline length (m) within which ``fraction`` of the observables' whitened
    information lies: the ``B_max`` of the search's step and inner working angle.

    ``uv_m`` (n_uv, 2), ``design`` [n_obs, 2 n_uv], ``errors`` [n_obs]. A calvis file's
    uv points are the fit's whole knot grid, out to its corners (9.16 m on the default
    grid), where the DISCOs see nothing; its information ends with the mask's splodges.
    With 0.99 this is 5.33-5.34 m on the AB Dor files and a simulated pair, against the
    mask's longest baseline, 5.28 m (an OIFITS file's longest point): the same data give
    one inner working angle in either format (99.9 % would be 5.69 m, the splodges' edge).
    """
    power = _point_power(design, errors)
    radius = np.hypot(uv_m[:, 0], uv_m[:, 1])
    order = np.argsort(radius, kind="stable")
    cumulative = np.cumsum(power[order])
    if not cumulative[-1] > 0:  # no information at all: the longest point
        return float(radius.max())
    inside = int(np.searchsorted(cumulative, fraction * cumulative[-1]))
    return float(radius[order][min(inside, len(order) - 1)])


def from_calvis(
    calvis: CalVis, source: str = "", silent_tolerance: float = SILENT_UV_TOLERANCE
) -> Observables:
    """Observables of a calvis file (DISCOs through the file's linear map), without the uv
    points the DISCOs barely see (:func:`silent_uv_points` with ``silent_tolerance``;
    0 leaves out only points whose columns are zero)."""
    sky_to_uv = np.asarray(calvis.sky_to_uv, dtype=float)
    uv_all = np.asarray(calvis.uv_m) @ sky_to_uv  # b_sky = S^T b, as rows
    longest = information_radius_m(uv_all, calvis.disco_matrix, calvis.errors)
    kept = ~silent_uv_points(calvis.disco_matrix, calvis.errors, silent_tolerance)
    uv_sky = uv_all[kept]
    n_uv = uv_sky.shape[0]
    wl = np.broadcast_to(calvis.wavelengths_m, (n_uv, calvis.wavelengths_m.size))
    w = np.broadcast_to(calvis.weights / calvis.weights.sum(), wl.shape)
    n_obs = calvis.n_obs
    design = np.asarray(calvis.disco_matrix)
    head, tail = _split_design(design[:, np.concatenate([kept, kept])])
    return Observables(
        uv_m=np.asarray(uv_sky),
        wavelengths_m=np.asarray(wl),
        weights=np.asarray(w),
        design_head=head,
        design_tail=tail,
        exp_rows=np.zeros(n_obs, dtype=bool),
        wrap_rows=np.zeros(n_obs, dtype=bool),
        data_raw=np.asarray(calvis.values),
        projection=None,
        errors=np.asarray(calvis.errors),
        kinds=tuple(KIND_NAMES.index(k) for k in calvis.kinds),
        filter_name=calvis.filter_name,
        source=source,
        target=calvis.target,
        n_photons=float(calvis.n_photons),
        photon_source="NPHOT" if np.isfinite(calvis.n_photons) else "",
        linear=True,
        sky_to_uv=cast(Matrix2, tuple(tuple(float(x) for x in row) for row in sky_to_uv)),
        longest_baseline_m=longest,
    )


CpCorrelation = Literal["baseline", "independent"]


def from_oifits(
    oi: OIFits,
    cp_correlation: CpCorrelation = "baseline",
    band_samples: int = OIFITS_BAND_SAMPLES,
    n_holes: int = 7,
) -> Observables:
    """Observables of an OIFITS file: V2 and closure phases, whitened.

    Parameters
    ----------
    cp_correlation
        How to treat closure phases when the file has no covariance: ``"baseline"``
        (default) builds the correlation implied by independent baseline phases, per
        exposure, from the triangles' station indices or coordinates
        (:func:`baseline_closure_covariance`); ``"independent"`` takes them as
        independent (as most peer tools do).
    band_samples
        Wavelengths sampling each channel's ``EFF_BAND`` (top hat, equal weights).
    n_holes
        Holes of the mask, used only for the photon-count estimate from closure phases.
    """
    uv: list[np.ndarray] = []
    waves: list[np.ndarray] = []
    bands: list[np.ndarray] = []
    # (indices into uv, coefficients)
    rows_amp: list[tuple[np.ndarray, np.ndarray]] = []
    rows_phase: list[tuple[np.ndarray, np.ndarray]] = []
    raw_data: list[np.ndarray] = []
    exp_rows: list[np.ndarray] = []
    wrap_rows: list[np.ndarray] = []
    kinds: list[np.ndarray] = []
    blocks_cov: list[np.ndarray] = []

    def add_uv(u: np.ndarray, v: np.ndarray, wave: np.ndarray, band: np.ndarray) -> np.ndarray:
        start = sum(len(x) for x in uv)
        uv.append(np.column_stack([u, v]))
        waves.append(wave)
        bands.append(band)
        return np.arange(start, start + len(u))

    if oi.vis2 is not None:
        v2 = oi.vis2
        index = add_uv(v2.u_m, v2.v_m, v2.wavelength_m, v2.bandwidth_m)
        rows_amp.append((index[:, None], np.full((len(index), 1), 2.0)))
        raw_data.append(v2.value)
        exp_rows.append(np.ones(len(index), bool))
        wrap_rows.append(np.zeros(len(index), bool))
        kinds.append(np.full(len(index), AMPLITUDE))
        blocks_cov.append(v2.covariance if v2.covariance is not None else np.diag(v2.error**2))
    if oi.t3 is not None:
        t3 = oi.t3
        i1 = add_uv(t3.u1_m, t3.v1_m, t3.wavelength_m, t3.bandwidth_m)
        i2 = add_uv(t3.u2_m, t3.v2_m, t3.wavelength_m, t3.bandwidth_m)
        i3 = add_uv(t3.u1_m + t3.u2_m, t3.v1_m + t3.v2_m, t3.wavelength_m, t3.bandwidth_m)
        rows_phase.append((np.column_stack([i1, i2, i3]), np.tile([1.0, 1.0, -1.0], (len(i1), 1))))
        raw_data.append(t3.phase_rad)
        exp_rows.append(np.zeros(len(i1), bool))
        wrap_rows.append(np.ones(len(i1), bool))
        kinds.append(np.full(len(i1), PHASE))
        if t3.covariance is not None:
            blocks_cov.append(t3.covariance)
        elif cp_correlation == "baseline":
            # Without STA_INDEX the baselines are known by their coordinates.
            legs = np.stack(
                [np.column_stack([t3.u1_m, t3.v1_m]), np.column_stack([t3.u2_m, t3.v2_m])], axis=1
            )
            blocks_cov.append(
                baseline_closure_covariance(
                    t3.stations, t3.wavelength_m, t3.error_rad, legs, t3.exposure
                )
            )
        else:
            blocks_cov.append(np.diag(t3.error_rad**2))

    uv_m = np.concatenate(uv)
    n_uv = uv_m.shape[0]
    n_amp = sum(len(r[0]) for r in rows_amp)
    n_raw = n_amp + sum(len(r[0]) for r in rows_phase)
    design = np.zeros((n_raw, 2 * n_uv))
    row = 0
    for index, coef in rows_amp:
        for k in range(len(index)):
            design[row, index[k]] = coef[k]
            row += 1
    for index, coef in rows_phase:
        for k in range(len(index)):
            np.add.at(design[row], n_uv + index[k], coef[k])
            row += 1

    wl, w = _band_sampling(np.concatenate(waves), np.concatenate(bands), band_samples)
    projection, errors, obs_kinds = _whitening(blocks_cov, np.concatenate(kinds))
    n_photons, photon_source = float("nan"), ""
    # NPHOT is amigo's keyword (not the OIFITS standard's): read from amigo's files only,
    # where it is the photons the fit used; another tool's may mean something else.
    counted = oi.header.get("NPHOT") if _written_by_amigo(oi.header) else None
    if isinstance(counted, bool) or not isinstance(counted, int | float):
        counted = np.nan
    if np.isfinite(counted) and counted > 0:
        n_photons, photon_source = counted, "NPHOT"
    elif oi.t3 is not None:
        # Ireland (2013): sigma_CP = N_h / N_p * sqrt(1.5 N_p) => N_p = 1.5 N_h^2 / sigma_CP^2.
        sigma_cp = float(np.median(oi.t3.error_rad))
        n_photons, photon_source = 1.5 * n_holes**2 / sigma_cp**2, "closure-phase errors"
    head, tail = _split_design(design)
    return Observables(
        uv_m=np.asarray(uv_m),
        wavelengths_m=np.asarray(wl),
        weights=np.asarray(w),
        design_head=head,
        design_tail=tail,
        exp_rows=np.asarray(np.concatenate(exp_rows)),
        wrap_rows=np.asarray(np.concatenate(wrap_rows)),
        data_raw=np.asarray(np.concatenate(raw_data)),
        projection=np.asarray(projection),
        errors=np.asarray(errors),
        kinds=tuple(int(k) for k in obs_kinds),
        filter_name=oi.filter_name,
        source=oi.path,
        target=oi.target,
        n_photons=n_photons,
        photon_source=photon_source,
    )


#: Baselines closer than this (m) are one baseline when closure phases give no station
#: indices (:func:`baseline_closure_covariance`): files round their coordinates, and an
#: aperture mask's baselines lie tenths of a metre apart.
BASELINE_MATCH_M = 5e-3


def _written_by_amigo(header: Any) -> bool:
    """Whether an OIFITS primary header is amigo's (``PROCSOFT = 'amigo <version>'``)."""
    return str(header.get("PROCSOFT", "")).strip().lower().startswith("amigo")


def baseline_closure_covariance(
    stations: np.ndarray | None,
    wavelength_m: np.ndarray,
    error_rad: np.ndarray,
    baselines_m: np.ndarray | None = None,
    exposure: np.ndarray | None = None,
) -> np.ndarray:
    """Closure-phase covariance implied by independent noise on each baseline phase.

    A triangle (a, b, c) measures ``phi_ab + phi_bc - phi_ac``; with independent baseline
    phases of equal variance, two closure phases sharing one baseline are correlated by
    +-1/3. The covariance is ``diag(sigma) (T T^T / 3) diag(sigma)`` with ``T`` the closure
    operator, built per spectral channel and per ``exposure`` (n,) (labels; ``None``: one
    exposure), whose baseline phases are independent of each other's. Its rank is
    n_baselines - (n_holes - 1) per channel and exposure.

    Baselines are known by their ``stations`` (n, 3), or by their coordinates where a
    file gives none or gives a triangle repeated stations (placeholders):
    ``baselines_m`` (n, 2, 2) holds each triangle's first two baselines ``(u1, v1), (u2,
    v2)``, the third being their sum, matched to a baseline seen before (or its reverse,
    of opposite phase) within :data:`BASELINE_MATCH_M`. A triangle listed twice within
    one exposure starts a second set of baseline phases: its k-th listing shares
    baselines with the k-th listings of the others only.
    """
    n = len(error_rad)
    exposure = np.zeros(n, dtype=int) if exposure is None else np.asarray(exposure)
    by_stations = stations is not None and all(
        len(set(np.asarray(row).tolist())) == 3 for row in stations
    )
    if not by_stations and baselines_m is None:
        raise ValueError("baseline_closure_covariance needs distinct stations or baselines_m")
    seen: dict[tuple[int, float], list[np.ndarray]] = {}  # baselines met, per group
    operator: dict[tuple, int] = {}
    listed: dict[tuple, int] = {}  # a triangle -> how many times it came before
    rows = np.zeros((n, 3), dtype=int)
    signs = np.zeros((n, 3))
    legs: list[tuple[Any, float]]
    for k in range(n):
        group = (int(exposure[k]), float(wavelength_m[k]))
        if by_stations:
            assert stations is not None
            a, b, c = (int(x) for x in stations[k])
            legs = [((min(p, q), max(p, q)), 1.0 if p < q else -1.0)
                    for p, q in ((a, b), (b, c), (a, c))]  # fmt: skip
        else:
            assert baselines_m is not None
            b1, b2 = np.asarray(baselines_m[k], dtype=float)
            known = seen.setdefault(group, [])
            legs = [_matched_baseline(known, leg) for leg in (b1, b2, -(b1 + b2))]
        triangle = (*group, *sorted(key for key, _ in legs))
        listing = listed.get(triangle, 0)
        listed[triangle] = listing + 1
        # T3 = V(b1) V(b2) V*(b1 + b2): the third leg's phase enters with a minus sign,
        # which the coordinates carry in -(b1 + b2) and the stations in the order (a, c).
        closure_signs = (1.0, 1.0, -1.0) if by_stations else (1.0, 1.0, 1.0)
        for j, ((key, sign), closure) in enumerate(zip(legs, closure_signs, strict=True)):
            rows[k, j] = operator.setdefault((*group, listing, key), len(operator))
            signs[k, j] = sign * closure
    matrix = np.zeros((n, len(operator)))
    for k in range(n):
        np.add.at(matrix[k], rows[k], signs[k])
    correlation = matrix @ matrix.T / 3.0
    return correlation * np.outer(error_rad, error_rad)


def _matched_baseline(known: list[np.ndarray], b: np.ndarray) -> tuple[int, float]:
    """The index of ``b`` among the baselines ``known`` (appended if new) and the sign of
    its phase relative to that baseline's (a reversed baseline has the opposite phase)."""
    for i, other in enumerate(known):
        if np.hypot(*(b - other)) < BASELINE_MATCH_M:
            return i, 1.0
        if np.hypot(*(b + other)) < BASELINE_MATCH_M:
            return i, -1.0
    known.append(np.array(b, dtype=float))
    return len(known) - 1, 1.0


def _whitening(
    covariances: Sequence[np.ndarray], raw_kinds: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block-wise eigen-rotation of the raw covariance: (P, errors, kinds)."""
    n_raw = sum(c.shape[0] for c in covariances)
    rows, errors, kinds = [], [], []
    start = 0
    for cov in covariances:
        size = cov.shape[0]
        sigma = np.sqrt(np.diag(cov))
        if np.allclose(cov, np.diag(np.diag(cov))):
            vectors, values = np.eye(size), sigma**2
        else:
            values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
            keep = values > COVARIANCE_RANK_TOL * values.max()
            values, vectors = values[keep], vectors[:, keep]
        block = np.zeros((values.size, n_raw))
        block[:, start : start + size] = vectors.T
        rows.append(block)
        errors.append(np.sqrt(values))
        kinds.append(np.full(values.size, raw_kinds[start]))
        start += size
    return np.concatenate(rows), np.concatenate(errors), np.concatenate(kinds)


def _band_sampling(wave: np.ndarray, band: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-hat sampling of each channel: (n_uv, n) wavelengths and equal weights."""
    offsets = (np.arange(n) + 0.5) / n - 0.5
    wl = wave[:, None] + band[:, None] * offsets[None, :]
    return wl, np.full(wl.shape, 1.0 / n)


def select_kinds(block: Observables, kinds: Sequence[str]) -> Observables | None:
    """The block restricted to observables of the given kinds (``None`` if none is left)."""
    wanted = {KIND_NAMES.index(k) for k in kinds}
    rows = np.array([k in wanted for k in block.kinds])
    if not rows.any():
        return None
    if rows.all():
        return block
    kept = tuple(k for k in block.kinds if k in wanted)
    if block.projection is None:  # raw observables are the independent ones
        head, tail = _split_design(block.design[rows])
        return dataclasses.replace(
            block,
            design_head=head,
            design_tail=tail,
            exp_rows=block.exp_rows[rows],
            wrap_rows=block.wrap_rows[rows],
            data_raw=block.data_raw[rows],
            errors=block.errors[rows],
            kinds=kept,
        )
    return dataclasses.replace(
        block, projection=block.projection[rows], errors=block.errors[rows], kinds=kept
    )


# ---------------------------------------------------------------------------- loading
#: Which observables each choice of ``observables`` keeps.
OBSERVABLE_CHOICES: dict[str, tuple[str, ...]] = {
    "all": ("amplitude", "phase"),
    "phase": ("phase",),
    "amplitude": ("amplitude",),
}


def load(
    path: str | os.PathLike[str],
    cp_correlation: CpCorrelation = "baseline",
    observables: str = "all",
) -> Observables:
    """Read a calvis or OIFITS file into :class:`Observables`; :class:`InputError` if neither.

    ``observables`` chooses what is fitted: ``"all"`` (default: DISCO amplitudes and
    phases, or V2 and closure phases), ``"phase"`` (kernel/closure phases only: for
    OIFITS files whose V2 are poorly calibrated) or ``"amplitude"``. Closure phases alone
    leave aliases of a 7-hole mask almost degenerate (docs/detect.md).
    """
    path = os.fspath(path)
    if observables not in OBSERVABLE_CHOICES:
        raise ValueError(f"observables must be one of {list(OBSERVABLE_CHOICES)}")
    require_file(path, "calvis or OIFITS file")
    # A file FITS cannot read (truncated, empty, not FITS) is refused in the reader's
    # words: the kind tests below would only say it is neither kind.
    open_fits(path).close()
    if is_calvis(path):
        block = from_calvis(read_calvis(path), source=path)
    elif is_oifits(path):
        block = from_oifits(read_oifits(path), cp_correlation=cp_correlation)
    else:
        raise InputError(path, "is neither an amigo calvis file nor an OIFITS file")
    wanted = OBSERVABLE_CHOICES[observables]
    selected = select_kinds(block, wanted)
    if selected is None:
        raise InputError(path, f"holds no {' or '.join(wanted)} observables")
    return selected


# ---------------------------------------------------------------------------- datasets
#: Single-precision counterparts of the double-precision dtypes.
_SINGLE = {np.dtype(np.float64): np.float32, np.dtype(np.complex128): np.complex64}


def _single(leaf: Any) -> Any:
    """A float64 (complex128) array leaf in float32 (complex64), NumPy staying NumPy and
    JAX staying JAX; any other leaf as given."""
    dtype = getattr(leaf, "dtype", None)
    if dtype not in _SINGLE:
        return leaf
    return leaf.astype(_SINGLE[np.dtype(dtype)])


def single_precision(tree: T) -> T:
    """``tree`` with every float64 and complex128 array leaf in single precision."""
    return cast(T, jax.tree_util.tree_map(_single, tree))


class Dataset(eqx.Module):
    """Several blocks fitted together: one contrast per filter, one error scale per group.

    A *group* is a (filter, observable kind) pair present in the data; the paper fits one
    multiplicative error scale per group.

    Attributes
    ----------
    blocks
        The data blocks (files).
    filters
        Distinct filter names, in order of first appearance.
    groups
        ``(filter, kind name)`` of each group.
    """

    blocks: tuple[Observables, ...]
    filters: tuple[str, ...] = eqx.field(static=True)
    groups: tuple[tuple[str, str], ...] = eqx.field(static=True)

    @classmethod
    def from_blocks(cls, blocks: Sequence[Observables]) -> Dataset:
        if not blocks:
            raise ValueError("a dataset needs at least one block of observables")
        filters = tuple(dict.fromkeys(b.filter_name for b in blocks))
        groups = tuple(
            (f, KIND_NAMES[k])
            for f in filters
            for k in range(len(KIND_NAMES))
            if any(b.filter_name == f and np.any(np.asarray(b.kinds) == k) for b in blocks)
        )
        return cls(blocks=tuple(blocks), filters=filters, groups=groups)

    @property
    def n_filters(self) -> int:
        return len(self.filters)

    @property
    def n_groups(self) -> int:
        return len(self.groups)

    def filter_index(self, block: int) -> int:
        """Index into :attr:`filters` of block ``block``."""
        return self.filters.index(self.blocks[block].filter_name)

    def group_index(self, block: int) -> np.ndarray:
        """(n_obs,) group index of each observable of block ``block``."""
        b = self.blocks[block]
        if len(b.kinds) != b.n_obs:
            # A program view's block (program_view): its groups are the view's arrays.
            raise ValueError("a block without its kinds has no group index here")
        lookup = {g: i for i, g in enumerate(self.groups)}
        return np.array([lookup[(b.filter_name, KIND_NAMES[k])] for k in np.asarray(b.kinds)])

    def group_counts(self) -> np.ndarray:
        """(n_groups,) number of observables in each group."""
        counts = np.zeros(self.n_groups)
        for i in range(len(self.blocks)):
            np.add.at(counts, self.group_index(i), 1)
        return counts

    def subset(self, filter_name: str) -> Dataset:
        """The blocks of one filter."""
        return Dataset.from_blocks([b for b in self.blocks if b.filter_name == filter_name])

    def single_precision(self) -> Dataset:
        """The same dataset with every float64 array in float32.

        For evaluations repeated thousands of times whose rounding is measured not to
        matter (NUTS's potential, :mod:`amigo.companions.posterior`): the observable
        matrices are then half the bytes to read and XLA's float32 matrix products and
        trigonometric functions on the CPU run about twice as fast. Residuals in float32
        carry a relative rounding of about 1e-7 of the observables, far below their errors.
        """
        return single_precision(self)

    def scale_vectors(self, group_scales: Array | np.ndarray) -> tuple[Array, ...]:
        """Per-block (n_obs,) error-scale vectors from (n_groups,) group scales (NumPy in,
        NumPy out: an eager JAX gather would be compiled for every block's shape)."""
        scales = group_scales if isinstance(group_scales, Array) else np.asarray(group_scales)
        return tuple(scales[self.group_index(i)] for i in range(len(self.blocks)))


# ---------------------------------------------------------------------------- program shapes
#: Rows of a padded block's two sections (:func:`program_view`) are a multiple of this.
ROW_MULTIPLE = 32
#: Levels per octave of a padded block's uv points (:func:`uv_bucket`).
UV_LEVELS_PER_OCTAVE = 4


def uv_bucket(n: int) -> int:
    """The number of uv points a block of ``n`` is padded to for compiled programs: the
    smallest level ``2^(k / 4)`` (rounded up to a multiple of 8) that holds ``n``.

    Levels a quarter of an octave apart pad by at most 19 % (9 % on average), and the
    points a calvis file keeps vary from target to target within a filter (its silent
    knots depend on the errors, :func:`silent_uv_points`: 1125-1172 of 1300 in F480M,
    922-966 in F430M, 799-803 in F380M on COM 1093), mostly within one level.
    """
    if n <= 8:
        return 8
    k = int(np.ceil(UV_LEVELS_PER_OCTAVE * np.log2(n) - 1e-9))
    level = int(np.ceil(2.0 ** (k / UV_LEVELS_PER_OCTAVE) / 8.0 - 1e-9)) * 8
    return max(level, -(-n // 8) * 8)


def _row_bucket(n: int) -> int:
    """Rows a section of ``n`` is padded to (an empty section stays empty)."""
    return -(-n // ROW_MULTIPLE) * ROW_MULTIPLE


def _padded_rows(values: Leaf, n_head: int, heads: int, tails: int, fill: Any) -> np.ndarray:
    """``values`` (n_obs, ...) with its head section padded to ``heads`` rows and its tail
    to ``tails`` rows, both with ``fill``."""
    values = np.asarray(values)
    out = np.full((heads + tails, *values.shape[1:]), fill, dtype=values.dtype)
    out[:n_head] = values[:n_head]
    out[heads : heads + len(values) - n_head] = values[n_head:]
    return out


def _padded_block(block: Observables) -> tuple[Observables, np.ndarray]:
    """A linear block padded to bucket sizes and its real rows' positions (n_obs,).

    Padded uv points have zero columns in the design (``uv = 0`` and the first point's
    band), padded observables zero rows with data 0 and error 1: their residuals are 0
    for every scene, so that every sum of squares and every product with the Jacobian is
    the block's own. Blocks with a whitening rotation (OIFITS) are not padded.
    """
    if block.projection is not None:
        return block, np.arange(block.n_obs)
    head, tail = np.asarray(block.design_head), np.asarray(block.design_tail)
    n_uv, n_head, n_tail = block.n_uv, head.shape[0], tail.shape[0]
    n_pad, heads, tails = uv_bucket(n_uv), _row_bucket(n_head), _row_bucket(n_tail)
    design_head = np.zeros((heads, n_pad), dtype=head.dtype)
    design_head[:n_head, :n_uv] = head
    design_tail = np.zeros((tails, 2 * n_pad), dtype=tail.dtype)
    design_tail[:n_tail, :n_uv] = tail[:, :n_uv]
    design_tail[:n_tail, n_pad : n_pad + n_uv] = tail[:, n_uv:]

    def points(values: Leaf) -> np.ndarray:
        values = np.asarray(values)
        edge = np.broadcast_to(values[:1], (n_pad - n_uv, *values.shape[1:]))
        return np.concatenate([values, edge])

    uv = np.zeros((n_pad, 2), dtype=np.asarray(block.uv_m).dtype)
    uv[:n_uv] = np.asarray(block.uv_m)
    padded = dataclasses.replace(
        block,
        uv_m=uv,
        wavelengths_m=points(block.wavelengths_m),
        weights=points(block.weights),
        design_head=design_head,
        design_tail=design_tail,
        exp_rows=_padded_rows(block.exp_rows, n_head, heads, tails, False),
        wrap_rows=_padded_rows(block.wrap_rows, n_head, heads, tails, False),
        data_raw=_padded_rows(block.data_raw, n_head, heads, tails, 0.0),
        errors=_padded_rows(block.errors, n_head, heads, tails, 1.0),
    )
    rows = np.concatenate([np.arange(n_head), heads + np.arange(n_tail)])
    return padded, rows


#: "Unknown" of a view block's numbers: one object, since two NaN objects are unequal and
#: would give every view a structure of its own (equinox and JAX compare static fields).
_UNKNOWN = float("nan")


def _anonymous(block: Observables) -> Observables:
    """The block without the metadata no program reads (file, target, photon count,
    orientation, longest baseline, kinds: the groups travel as arrays instead)."""
    return dataclasses.replace(
        block,
        kinds=(),
        source="",
        target="",
        n_photons=_UNKNOWN,
        photon_source="",
        sky_to_uv=((1.0, 0.0), (0.0, 1.0)),
        longest_baseline_m=_UNKNOWN,
    )


@dataclasses.dataclass(frozen=True)
class ProgramView:
    """A dataset as the compiled programs take it (:func:`program_view`). Programs get
    ``dataset`` and ``groups``; ``rows`` stays outside them (its values would key them).

    Attributes
    ----------
    dataset
        Its blocks padded to bucket sizes and without the metadata no program reads.
    groups
        Per block, (n_obs padded,) int32 the group index of each observable; padded rows
        point at ``n_groups``, an inert slot whose error scale is 1.
    rows
        Per block, (n_obs,) the positions of the block's own observables in the padded
        ones, to take a program's per-observable outputs back to the block's.
    """

    dataset: Dataset
    groups: tuple[Leaf, ...]
    rows: tuple[np.ndarray, ...]

    def scale_vectors(self, group_scales: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per padded block, (n_obs padded,) error-scale vectors from (n_groups,) group
        scales (:func:`padded_scale_vector`)."""
        return tuple(padded_scale_vector(group_scales, groups) for groups in self.groups)


def padded_scale_vector(group_scales: np.ndarray, groups: Leaf) -> np.ndarray:
    """Each observable's error scale from (n_groups,) group scales and its group index
    ``groups`` (a :class:`ProgramView`'s, padded rows at ``n_groups``): 1 at the padded
    rows, whose residuals are 0."""
    return np.append(np.asarray(group_scales, dtype=float), 1.0)[np.asarray(groups)]


#: Views of living datasets, by the dataset's id: (a weak reference to it, its view),
#: oldest first. An entry leaves when its dataset dies (the reference's callback).
_VIEWS: dict[int, tuple[weakref.ref, ProgramView]] = {}
#: The keys in the order their views were made (some may have left already): eviction
#: reads this, never iterates the dict, which a garbage-collector callback may change.
_ORDER: collections.deque[int] = collections.deque()
_VIEWS_LOCK = threading.Lock()
#: How many views are kept at most (a detection alternates between a few datasets: the
#: joint one and each filter's).
VIEWS_KEPT = 8


def _forget(key: int, ref: weakref.ref) -> None:
    """A dataset died: its view goes (unless the key already holds another's). Called by
    the garbage collector, so without the lock (one dict operation is atomic)."""
    kept = _VIEWS.get(key)
    if kept is not None and kept[0] is ref:
        _VIEWS.pop(key, None)


def program_view(dataset: Dataset) -> ProgramView:
    """``dataset`` shaped for programs shared across targets.

    Compiled programs are keyed on their arguments' shapes and static metadata
    (:mod:`amigo.programs`): a calvis file's DISCO count and the uv points left after its
    silent knots differ from target to target, and with them every program of the
    detection (NUTS's took ~17 s to compile for AB Dor on 2 CPU cores). Padded to bucket
    sizes (:func:`uv_bucket`, rows to a multiple of :data:`ROW_MULTIPLE`) with inert
    points and observables, and stripped of the file's metadata, another target of the
    same filters usually lands on the same shapes, and so on the programs already on disk.
    The values of the residuals at the real rows, of every sum of squares and of every
    product with a Jacobian are the block's own (to rounding).

    A dataset on the device (``jax.device_put``) gets a view on the device, made once
    and kept while the dataset lives (at most :data:`VIEWS_KEPT` of them): every compiled
    call would otherwise copy the padded matrices to the device again.
    """
    key = id(dataset)
    with _VIEWS_LOCK:  # fits run side by side in threads
        kept = _VIEWS.get(key)
        if kept is not None and kept[0]() is dataset:
            return kept[1]
        view = _program_view(dataset)
        if any(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(dataset)):
            view = dataclasses.replace(
                view, dataset=jax.device_put(view.dataset), groups=jax.device_put(view.groups)
            )
        ref = weakref.ref(dataset, functools.partial(_forget, key))
        _VIEWS[key] = (ref, view)
        _ORDER.append(key)
        while len(_VIEWS) > VIEWS_KEPT and _ORDER:
            _VIEWS.pop(_ORDER.popleft(), None)
        if len(_ORDER) > 4 * VIEWS_KEPT:  # keys whose views died with their datasets
            live = [k for k in _ORDER if k in _VIEWS]
            _ORDER.clear()
            _ORDER.extend(live)
        return view


def _program_view(dataset: Dataset) -> ProgramView:
    blocks, groups, rows = [], [], []
    for i, block in enumerate(dataset.blocks):
        padded, real = _padded_block(block)
        index = np.full(padded.n_obs, dataset.n_groups, dtype=np.int32)
        index[real] = dataset.group_index(i)
        blocks.append(_anonymous(padded))
        groups.append(index)
        rows.append(real)
    view = dataclasses.replace(dataset, blocks=tuple(blocks))
    return ProgramView(dataset=view, groups=tuple(groups), rows=tuple(rows))
