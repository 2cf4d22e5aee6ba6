"""The first group's photons: a known reset level (superbias) lets the first read count.

A pixel's ramp in one integration, read at groups ``k = 1..n`` (NISRAPID: one frame per
group, the first read one group time ``t_g`` after the reset), is ::

    r_k = b + e + Q_k + R_k,

``b`` the pixel's mean reset level (the *superbias*, a property of the detector), ``e``
this integration's departure from it (reset noise, kTC: the same for every read of the
integration), ``Q_k`` the accumulated signal (DN) and ``R_k`` read noise. Group
differences ``d_k = r_{k+1} - r_k`` cancel ``b + e`` and with it the signal ``Q_1`` that
arrived before the first read: a slope fit measures ``n - 1`` of the ``n`` group times'
photons (half of them at two groups). With ``b`` known, ``r_1 - b = Q_1 + e + R_1`` is
one more measurement of the signal, of a group time's photons, whose noise adds the
reset noise (already in the ramp's sample covariance, since ``e`` varies between the
integrations it is estimated from) and the superbias' own error.

So the first group enters the likelihood as one more value in front of the slopes ::

    v = (r_1 - b_hat, d_1, ..., d_{n-1}),   E[v] = (Q_1, Q_2 - Q_1, ...),

every entry expecting ``t_g`` times the count rate under linear accumulation, with
covariance (``C`` the ramp's, ``RAMP_COV``; ``s^2`` the variance of ``b_hat``) ::

    Cov(v)_00 = C_11 + s^2,   Cov(v)_0k = C_1,k+1 - C_1,k,   Cov(v)_jk = SLOPE_COV.

Marginalising the unknown ``b`` over the Gaussian prior ``N(b_hat, s^2)`` is exactly
the ``s^2`` in ``Cov(v)_00``; as ``s -> inf`` the first value carries no information and
the likelihood is the slopes' again. A pixel whose superbias is unknown gets
:data:`UNKNOWN_VARIANCE_DN2`, i.e. that limit, so every pixel keeps the same number of
values. With one group (``n = 1``) the first value is all there is.

The superbias is estimated (:func:`estimate_superbias`) from calslope files of the same
detector: dark exposures are the clean source (no signal to remove), as the JWST
pipeline's superbias reference is; exposures with light work too, their signal before
the first read removed with the mean slope (exact for linear accumulation, biased by the
ramp's curvature on bright pixels, which is why darks are preferred).

Shapes: ``(ny, nx)`` images, ``(n, ny, nx)`` ramps, ``(n, n, ny, nx)`` covariances; DN.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from amigo.errors import InputError

if TYPE_CHECKING:
    from amigo.io.calslope import CalSlope

#: Variance (DN^2) standing for "superbias unknown": ~1e6 DN rms, so the first value's
#: weight is < 1e-8 of a slope's and the likelihood is, to float precision, the slopes'.
UNKNOWN_VARIANCE_DN2 = 1.0e12


@dataclass(frozen=True)
class Superbias:
    """Mean reset level of each pixel and the variance of that estimate.

    Attributes
    ----------
    level_dn
        (ny, nx) superbias, DN (0 where unknown).
    variance_dn2
        (ny, nx) variance of ``level_dn``, DN^2 (:data:`UNKNOWN_VARIANCE_DN2` where
        unknown).
    n_files
        Number of calslope files it was estimated from.
    """

    level_dn: np.ndarray
    variance_dn2: np.ndarray
    n_files: int = 1

    @classmethod
    def where_known(
        cls, level_dn: np.ndarray, variance_dn2: np.ndarray, known: np.ndarray, n_files: int
    ) -> Superbias:
        """The estimate where ``known`` (ny, nx), "unknown" (0, and
        :data:`UNKNOWN_VARIANCE_DN2`) elsewhere."""
        return cls(
            level_dn=np.where(known, level_dn, 0.0),
            variance_dn2=np.where(known, variance_dn2, UNKNOWN_VARIANCE_DN2),
            n_files=n_files,
        )

    def summary(self) -> dict[str, int | float]:
        """Files, pixels known and the median error (DN) of the known pixels (a model's
        metadata records it; ``amigo fit`` reports it)."""
        known = self.known
        error = np.sqrt(np.median(self.variance_dn2[known])) if known.any() else float("nan")
        return {
            "files": int(self.n_files),
            "pixels_known": int(known.sum()),
            "median_error_dn": round(float(error), 4),
        }

    @property
    def known(self) -> np.ndarray:
        """(ny, nx) True where the superbias was measured (the test is against half the
        "unknown" variance: float32 storage, as in a model file, rounds it down)."""
        return self.variance_dn2 < 0.5 * UNKNOWN_VARIANCE_DN2


def superbias_of(product: CalSlope) -> Superbias:
    """Estimate the superbias from one calslope file: ``b_hat = r_1 - mean(d)``.

    The mean group difference ``mean(d)`` (DN per group) is the signal one group time
    accumulates under linear accumulation, hence the signal before the first read; its
    variance and its covariance with ``r_1`` come from ``RAMP_COV``, so ::

        Var(b_hat) = a^T C a,   a = (1, 0, ..., 0) - (e_n - e_1) / (n - 1)

    (``mean(d) = (r_n - r_1) / (n - 1)``). This variance includes the reset noise of the
    file's integrations, averaged over them. Pixels flagged in BADPIX or with an
    undefined ramp are unknown.
    """
    path = product.path or "<calslope>"
    ramp = np.asarray(product.ramp_dn, np.float64)
    cov = np.asarray(product.ramp_cov_dn2, np.float64)
    n = ramp.shape[0]
    if n < 2:
        raise InputError(
            path, "a superbias needs at least 2 groups (1 cannot tell bias from light)"
        )
    a = np.zeros(n)
    a[0] = 1.0 + 1.0 / (n - 1)
    a[-1] -= 1.0 / (n - 1)
    level = np.einsum("k,kyx->yx", a, ramp)
    variance = np.einsum("j,jkyx,k->yx", a, cov, a)
    known = ~np.asarray(product.badpix, bool) & np.isfinite(level) & np.isfinite(variance)
    known &= variance > 0
    return Superbias.where_known(level, variance, known, n_files=1)


def estimate_superbias(products: list[CalSlope]) -> Superbias:
    """Inverse-variance mean of :func:`superbias_of` over calslope files of one detector
    (same subarray shape); raises :class:`InputError` naming a file of another shape."""
    if not products:
        raise ValueError("no calslope file to estimate a superbias from")
    parts = [superbias_of(p) for p in products]
    shape = parts[0].level_dn.shape
    for product, part in zip(products, parts, strict=True):
        if part.level_dn.shape != shape:
            raise InputError(
                product.path or "<calslope>",
                f"shape {part.level_dn.shape} differs from the other superbias files' {shape}",
            )
    weights = np.array([np.where(p.known, 1.0 / p.variance_dn2, 0.0) for p in parts])
    total = weights.sum(axis=0)
    known = total > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.einsum("fyx,fyx->yx", weights, np.array([p.level_dn for p in parts])) / total
        variance = 1.0 / total
    return Superbias.where_known(level, variance, known, n_files=len(parts))


def first_group_values(
    product: CalSlope, superbias: Superbias
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The values ``v`` of the module notes, their covariance and support.

    Returns ``(values, covariance, support)``: (n, ny, nx) DN per group, (n, n, ny, nx)
    DN^2 and (n, ny, nx) integrations, ``n`` = NGROUPS (the first group less the
    superbias, then the ``n - 1`` slopes).
    """
    path = product.path or "<calslope>"
    ramp = np.asarray(product.ramp_dn, np.float64)
    cov = np.asarray(product.ramp_cov_dn2, np.float64)
    n, ny, nx = ramp.shape
    if superbias.level_dn.shape != (ny, nx):
        raise InputError(
            path, f"shape {(ny, nx)} differs from the superbias' {superbias.level_dn.shape}"
        )
    m = n - 1
    values = np.empty((n, ny, nx))
    values[0] = ramp[0] - superbias.level_dn
    values[1:] = np.asarray(product.slope_dn, np.float64)
    covariance = np.empty((n, n, ny, nx))
    covariance[1:, 1:] = np.asarray(product.slope_cov_dn2, np.float64)
    covariance[0, 0] = cov[0, 0] + superbias.variance_dn2
    if m:
        # Cov(r_1, r_{k+1} - r_k): the read noise of r_1 against d_1, photon noise is not
        # shared (a group's photons are in r_1 or in the later differences, not both).
        across = cov[0, 1:] - cov[0, :-1]  # (m, ny, nx)
        covariance[0, 1:] = across
        covariance[1:, 0] = across
    # A pixel whose first group is undefined (no integration kept it) keeps its slopes:
    # the first value is made uninformative rather than the pixel lost.
    lost = ~(np.isfinite(values[0]) & np.isfinite(covariance[0]).all(axis=0))
    values[0][lost] = 0.0
    covariance[0, :, lost] = 0.0
    covariance[:, 0, lost] = 0.0
    covariance[0, 0][lost] = UNKNOWN_VARIANCE_DN2
    support = np.concatenate(
        [np.asarray(product.ramp_support, np.float64)[:1], np.asarray(product.slope_support)]
    )
    return values, covariance, support


def with_first_group(product: CalSlope, superbias: Superbias) -> CalSlope:
    """``product`` with its slopes replaced by :func:`first_group_values`: every reader
    of ``SLOPE``/``SLOPE_COV``/``SLOPE_SUP`` (the likelihood, the full detector's
    correction) then uses the first group as one more "slope" that expects ``t_g`` times
    the rate. Its ``ramp_*`` arrays are untouched."""
    values, covariance, support = first_group_values(product, superbias)
    return dataclasses.replace(
        product, slope_dn=values, slope_cov_dn2=covariance, slope_support=support
    )
