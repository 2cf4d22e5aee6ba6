"""Contrast limits: Ruffio et al. (2018), Absil et al. (2011) style, and the photon rule.

Both limits are computed at every grid position from the grid search on the
companion-subtracted data (the found companions are part of the background scene and the
errors carry the fitted ``sigma_scale``); per position the search gives the linear
contrast estimate ``c`` (signed) and its error ``s``.

* **Ruffio et al. (2018)**: a Bayesian upper limit. With a uniform prior on ``c >= 0``
  the posterior is the normal ``N(c, s)`` truncated at zero; the limit at confidence
  ``q`` (3 sigma: ``q = Phi(3)``) solves ``P(c' < limit | c' >= 0) = q``.
* **Absil et al. (2011) style**: a frequentist rejection. Assume the data are consistent
  with the background scene (reduced chi2 ``chi2_0 / N``); a companion of flux ratio
  ``c'`` at the position is excluded at ``n`` sigma when the chi2 of the data under
  "background + companion", normalised by the background's reduced chi2, is so large that
  a chi2 distribution with ``N`` degrees of freedom exceeds it with probability below the
  two-sided normal tail of ``n``. Using the local quadratic form of chi2 in ``c'`` the
  limit is ``c + sqrt(c^2 + K s^2)``, ``K = (t_n / N - 1) chi2_0``, ``t_n`` the chi2
  quantile. It grows with the number of observables and is more conservative than Ruffio.
  amigo counts the observables a companion in the searched field can move: the residuals
  projected on that field's signal subspace (:mod:`amigo.companions.subspace`; ``k`` =
  109 of 928 DISCOs of a simulated F480M exposure within 450 mas, 362-406 within the
  default 1000 mas), whose chi2 has ``k`` degrees of
  freedom; the test on every observable (``N``) is kept beside it as ``absil_all``.
* **Photon rule of thumb** (paper, after Ireland 2013 and JDox): contrast ~
  ``sqrt(100 / N_photons)``, i.e. ``dmag = 2.5 log10(sqrt(N_p / 100))``.

Azimuthal curves are the mean and standard deviation of the limit (in magnitudes) over
annuli, as in the paper's figure.

**Combined** (more than one filter): the limit on a companion with the same flux ratio in
every filter (grey against the star; :func:`combine_filters`), the filters' estimates
averaged with inverse-variance weights. Its photon rule counts the photons of all filters.

Separations are also given in units of ``lambda / D``: ``lambda`` the mean wavelength of
the filter's observables (of all filters for the combined curve), ``D`` the circumscribed
pupil diameter :data:`amigo.niriss.PUPIL_DIAMETER_M` (6.603 m; 1.6 % more ``lambda/D``
per mas than with the 6.5 m often quoted).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import special, stats

from amigo.companions.grid import ContrastMap, GridResult
from amigo.companions.models import MAS_TO_RAD
from amigo.companions.subspace import COMBINED, SignalSpace
from amigo.niriss import PUPIL_DIAMETER_M

#: Confidence of a "3-sigma" upper limit, Phi(3) (one-sided).
THREE_SIGMA = float(stats.norm.cdf(3.0))
#: Flux ratio used in place of limits that are not positive (no information).
CONTRAST_CEILING = 1.0


def lambda_over_d_mas(wavelength_m: float) -> float:
    """``lambda / D`` in milliarcseconds, ``D`` the circumscribed pupil
    :data:`PUPIL_DIAMETER_M`."""
    return wavelength_m / PUPIL_DIAMETER_M / MAS_TO_RAD


def ruffio_upper_limit(
    contrast: npt.ArrayLike, sigma: npt.ArrayLike, confidence: float = THREE_SIGMA
) -> np.ndarray:
    """Upper limit on a flux ratio from a normal estimate truncated to positive values.

    Solves ``[Phi((u - c)/s) - Phi(-c/s)] / [1 - Phi(-c/s)] = confidence`` for ``u``,
    written with log tails so that strongly negative estimates stay accurate.
    """
    c = np.asarray(contrast, dtype=float)
    s = np.asarray(sigma, dtype=float)
    # 1 - q = (1 - confidence) * Phi(c / s); u = c + s * isf(1 - q).
    log_tail = np.log1p(-confidence) + special.log_ndtr(c / s)
    return c - s * special.ndtri_exp(log_tail)


def absil_limit(
    contrast: npt.ArrayLike,
    sigma: npt.ArrayLike,
    chi2_background: float,
    n_obs: int,
    n_sigma: float = 3.0,
) -> np.ndarray:
    """Flux ratio excluded at ``n_sigma`` by the chi2 test described in the module doc."""
    c = np.asarray(contrast, dtype=float)
    s = np.asarray(sigma, dtype=float)
    p = 2.0 * stats.norm.sf(n_sigma)
    t_n = stats.chi2.isf(p, n_obs)
    k = max(t_n / n_obs - 1.0, 0.0) * chi2_background
    return c + np.sqrt(c**2 + k * s**2)


def photon_limit_dmag(n_photons: float) -> float:
    """The photon-noise rule of thumb ``2.5 log10(sqrt(N_p / 100))`` in magnitudes."""
    return float(2.5 * np.log10(np.sqrt(n_photons / 100.0)))


def to_dmag(contrast: np.ndarray) -> np.ndarray:
    """Limits as magnitudes; non-positive or non-finite limits become 0 mag (no limit)."""
    c = np.asarray(contrast, dtype=float)
    c = np.where(np.isfinite(c) & (c > 0), np.minimum(c, CONTRAST_CEILING), CONTRAST_CEILING)
    return -2.5 * np.log10(c)


def azimuthal_profile(
    radius: np.ndarray, values: np.ndarray, valid: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation of ``values`` in annuli ``edges``.

    Returns ``(centres, mean, std, count)``; empty annuli give NaN.
    """
    which = np.digitize(radius[valid], edges) - 1
    v = values[valid]
    n_bins = edges.size - 1
    inside = (which >= 0) & (which < n_bins)
    count = np.bincount(which[inside], minlength=n_bins)
    total = np.bincount(which[inside], weights=v[inside], minlength=n_bins)
    squares = np.bincount(which[inside], weights=v[inside] ** 2, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
        var = np.where(count > 0, squares / count - mean**2, np.nan)
    return 0.5 * (edges[1:] + edges[:-1]), mean, np.sqrt(np.clip(var, 0, None)), count


def combine_filters(maps: Sequence[ContrastMap]) -> ContrastMap:
    """One contrast map for a companion of the same flux ratio in every filter.

    Per position the filters' signed estimates ``c_f +- s_f`` are independent, so the grey
    companion's estimate is their inverse-variance mean ``c = sum(c_f / s_f^2) / sum(1 /
    s_f^2)`` with ``s = sum(1 / s_f^2)^(-1/2)`` and ``dchi2 = c^2 / s^2``. The Absil test
    counts every filter's observables (``n_obs`` and ``chi2_background`` summed); the inner
    working angle is the largest of the filters'.
    """
    weights = [np.where(np.isfinite(m.sigma) & (m.sigma > 0), m.sigma**-2.0, 0.0) for m in maps]
    total = np.sum(weights, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        contrast = np.sum(
            [w * np.nan_to_num(m.contrast) for w, m in zip(weights, maps, strict=True)], axis=0
        ) / np.where(total > 0, total, np.nan)
        sigma = np.where(total > 0, total**-0.5, np.nan)
    return ContrastMap(
        filter_name=COMBINED,
        contrast=contrast,
        sigma=sigma,
        dchi2=np.nan_to_num((contrast / sigma) ** 2),
        chi2_background=float(sum(m.chi2_background for m in maps)),
        n_obs=int(sum(m.n_obs for m in maps)),
        iwa_mas=float(max(m.iwa_mas for m in maps)),
    )


@dataclass(frozen=True)
class ContrastCurve:
    """Contrast limits of one filter (or of all, ``filter_name == "combined"``): maps
    (n_y, n_x) and azimuthal curves, in magnitudes; ``wavelength_m`` the mean wavelength
    of its observables (for :attr:`sep_lambda_d`; NaN where unknown)."""

    filter_name: str
    sep_mas: np.ndarray
    ruffio_dmag: np.ndarray
    ruffio_dmag_std: np.ndarray
    absil_dmag: np.ndarray
    absil_dmag_std: np.ndarray
    ruffio_map_dmag: np.ndarray
    absil_map_dmag: np.ndarray
    n_sigma: float
    photon_limit_dmag: float | None = None
    wavelength_m: float = float("nan")
    #: The Absil test on every observable (``N`` degrees of freedom), azimuthal mean.
    absil_all_dmag: np.ndarray | None = None
    #: Degrees of freedom of the Absil test (the signal subspace's ``k``) and ``N``.
    absil_dof: int | None = None
    n_obs: int | None = None

    @property
    def sep_lambda_d(self) -> np.ndarray:
        """Separations in units of ``lambda / D`` (D: :data:`PUPIL_DIAMETER_M`)."""
        return self.sep_mas / lambda_over_d_mas(self.wavelength_m)


def contrast_limits(
    result: GridResult,
    n_sigma: float = 3.0,
    bin_width_mas: float | None = None,
    photon_counts: Mapping[str, float] | None = None,
    wavelengths_m: Mapping[str, float] | None = None,
    signal_spaces: Mapping[str, SignalSpace] | None = None,
) -> list[ContrastCurve]:
    """Ruffio and Absil limits per filter from a grid search on companion-subtracted data,
    then (with more than one filter) those of all filters combined (:func:`combine_filters`).

    ``photon_counts`` and ``wavelengths_m`` are per filter; the combined curve sums the
    photons (when every filter has a count) and takes the mean of the wavelengths.
    ``signal_spaces`` (per filter and combined,
    :func:`amigo.companions.subspace.signal_spaces`): the Absil test counts the
    residuals' chi2 in each one's signal subspace; a curve without one, every observable.
    """
    grid = result.grid
    width = bin_width_mas or grid.step_mas
    photons = dict(photon_counts or {})
    waves = dict(wavelengths_m or {})
    maps = list(result.maps)
    if len(maps) > 1:
        maps.append(combine_filters(result.maps))
        names = [m.filter_name for m in result.maps]
        if all(photons.get(f) for f in names):
            photons[COMBINED] = float(sum(photons[f] for f in names))
        if all(f in waves for f in names):
            waves[COMBINED] = float(np.mean([waves[f] for f in names]))
    spaces = dict(signal_spaces or {})
    curves = []
    for m in maps:
        valid = grid.valid(m.iwa_mas) & np.isfinite(m.sigma)
        edges = np.arange(m.iwa_mas, grid.rmax_mas + 0.5 * width, width)
        if edges.size < 2:
            edges = np.array([m.iwa_mas, grid.rmax_mas])
        confidence = float(stats.norm.cdf(n_sigma))
        ruffio = to_dmag(ruffio_upper_limit(m.contrast, m.sigma, confidence))
        every = to_dmag(absil_limit(m.contrast, m.sigma, m.chi2_background, m.n_obs, n_sigma))
        space = spaces.get(m.filter_name)
        absil = (
            every
            if space is None
            else to_dmag(
                absil_limit(m.contrast, m.sigma, space.chi2_background, space.dof, n_sigma)
            )
        )
        centres, r_mean, r_std, count = azimuthal_profile(grid.radius_mas, ruffio, valid, edges)
        _, a_mean, a_std, _ = azimuthal_profile(grid.radius_mas, absil, valid, edges)
        _, all_mean, _, _ = azimuthal_profile(grid.radius_mas, every, valid, edges)
        keep = count > 0
        n_photons = photons.get(m.filter_name)
        curves.append(
            ContrastCurve(
                filter_name=m.filter_name,
                sep_mas=centres[keep],
                ruffio_dmag=r_mean[keep],
                ruffio_dmag_std=r_std[keep],
                absil_dmag=a_mean[keep],
                absil_dmag_std=a_std[keep],
                ruffio_map_dmag=np.where(valid, ruffio, np.nan),
                absil_map_dmag=np.where(valid, absil, np.nan),
                n_sigma=n_sigma,
                photon_limit_dmag=(
                    photon_limit_dmag(n_photons) if n_photons and np.isfinite(n_photons) else None
                ),
                wavelength_m=float(waves.get(m.filter_name, np.nan)),
                absil_all_dmag=all_mean[keep],
                absil_dof=m.n_obs if space is None else space.dof,
                n_obs=m.n_obs,
            )
        )
    return curves
