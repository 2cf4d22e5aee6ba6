"""What makes a grid-search peak a detection: trials, the working angle, the spectrum.

A companion search tests every position of a grid, so its best peak is the maximum of
many chi2 improvements; residual calibration structure adds peaks that a point source
does not explain. Three tests turn a peak into a detection (``amigo detect``):

1. **Trials (the look-elsewhere effect).** The local significance ``n_loc`` comes from
   the chi2 gain ``dchi2`` with one degree of freedom per filter (the contrasts), the
   position being chosen by the search. With ``N`` independent positions searched, the
   probability that noise alone gives a peak at least this high anywhere is

       FAP = 1 - (1 - p_loc)^N,    p_loc = P(chi2_F > dchi2),

   and the *global* significance is the Gaussian-equivalent of ``FAP`` (two-sided, as
   :func:`~amigo.companions.grid.sigma_from_chi2`). ``N`` is the searched area over the
   area of a resolution element, a disc of radius ``lambda / (2 B_max)`` (the inner
   working angle): ``N = (r_max^2 - r_iwa^2) / r_iwa^2``. Its calibration against
   Monte-Carlo null data sets is tested in tests/test_companions_significance.py.
2. **Inner working angle.** Inside ``lambda / (2 B_max)`` a companion's separation and
   contrast are degenerate (its phases grow as ``c r^2``) and indistinguishable from a
   small calibration error of the primary's visibilities: a candidate that the joint fit
   moves there is reported as such, never as a detection.
3. **A stellar spectrum.** A real companion's contrast changes smoothly across the AMI
   filters (3.8-4.8 um). The per-filter contrasts ``c_f`` (with their errors) are fitted
   with ``a exp(s (lambda_f - lambda_0))`` for any ``a >= 0`` and a colour ``|s|`` up to
   :data:`MAX_COLOUR_MAG_PER_UM` (a late T dwarf against an A star is about 2 mag per
   micron across [3.6]-[4.5]); a chi2 with a tail probability below
   :data:`SPECTRUM_P_MIN` marks contrasts that no star or brown dwarf has, such as
   dmag 25 in one filter and 0.2 in the next.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special, stats

#: Steepest companion-to-star colour admitted, in magnitudes per micron of wavelength.
MAX_COLOUR_MAG_PER_UM = 3.0
#: Tail probability below which per-filter contrasts are inconsistent with a spectrum.
SPECTRUM_P_MIN = 1e-3


def log_chi2_sf(x: np.ndarray | float, dof: int) -> np.ndarray:
    """``log P(chi2_dof > x)``, finite far into the tail (where SciPy underflows, the
    asymptotic ``Gamma(s, y) ~ y^(s-1) e^-y (1 + (s-1)/y)`` with ``s = dof/2, y = x/2``)."""
    xs = np.clip(np.asarray(x, dtype=float), 0.0, None)
    log_p = np.asarray(stats.chi2.logsf(xs, dof), dtype=float)
    lost = ~np.isfinite(log_p)
    if np.any(lost):
        s, y = 0.5 * dof, 0.5 * xs[lost]
        log_p[lost] = (s - 1) * np.log(y) - y - special.gammaln(s) + np.log1p((s - 1) / y)
    return log_p


def sigma_from_log_p(log_p: np.ndarray | float) -> np.ndarray:
    """Gaussian-equivalent significance ``n`` whose two-sided tail is ``exp(log_p)``."""
    log_p = np.minimum(np.asarray(log_p, dtype=float), 0.0)
    return np.clip(-special.ndtri_exp(log_p - np.log(2.0)), 0.0, None)


def effective_trials(rmax_mas: float, iwa_mas: float) -> float:
    """Independent positions in a search out to ``rmax_mas`` outside ``iwa_mas``: the
    annulus area over the area of a resolution element of radius ``iwa_mas`` (>= 1)."""
    return float(max(1.0, (rmax_mas**2 - iwa_mas**2) / iwa_mas**2))


@dataclass(frozen=True)
class Significance:
    """A peak's significance: local, global (trials-corrected) and its false-alarm
    probability; ``trials`` the number of independent positions it was corrected for."""

    local_sigma: float
    sigma: float
    false_alarm_probability: float
    trials: float


def significance(dchi2: float, dof: int, trials: float) -> Significance:
    """The local and global significance of a chi2 gain ``dchi2`` with ``dof`` contrasts,
    the best of ``trials`` independent positions."""
    log_p = float(log_chi2_sf(dchi2, dof))
    if log_p > -25.0:  # 1 - (1 - p)^N, exactly
        log_fap = float(np.log(-np.expm1(trials * np.log1p(-np.exp(log_p)))))
    else:  # N p, to double precision
        log_fap = np.log(trials) + log_p
    log_fap = min(log_fap, 0.0)
    return Significance(
        local_sigma=float(sigma_from_log_p(log_p)),
        sigma=float(sigma_from_log_p(log_fap)),
        false_alarm_probability=float(np.exp(log_fap)),
        trials=float(trials),
    )


@dataclass(frozen=True)
class SpectrumTest:
    """The fit of per-filter contrasts by a smooth spectrum: its chi2, degrees of
    freedom, tail probability and best colour (mag per micron, positive: fainter in the
    red)."""

    chi2: float
    dof: int
    p_value: float
    colour_mag_per_um: float

    @property
    def consistent(self) -> bool:
        return self.p_value >= SPECTRUM_P_MIN


def spectrum_test(
    contrasts: np.ndarray, errors: np.ndarray, wavelengths_um: np.ndarray
) -> SpectrumTest:
    """Test contrasts ``c_f +- sigma_f`` at ``wavelengths_um`` (F,) against
    ``a exp(s (lambda - lambda_0))``, ``a >= 0``, ``|s|`` up to the steepest colour.

    The colour is searched on a fine grid, ``a`` solved by weighted least squares for
    each. Degrees of freedom: ``F - 2`` for three or more filters; with two filters any
    pair of positive contrasts fits unless the colour bound binds, so one.
    """
    c = np.asarray(contrasts, dtype=float)
    w = 1.0 / np.asarray(errors, dtype=float) ** 2
    x = np.asarray(wavelengths_um, dtype=float) - float(np.mean(wavelengths_um))
    if c.size < 2:
        return SpectrumTest(0.0, 0, 1.0, 0.0)
    s_max = 0.4 * np.log(10.0) * MAX_COLOUR_MAG_PER_UM  # magnitudes -> natural log
    best = (np.inf, 0.0)
    for s in np.linspace(-s_max, s_max, 241):
        shape = np.exp(s * x)
        a = max(float(np.sum(w * c * shape) / np.sum(w * shape**2)), 0.0)
        chi2 = float(np.sum(w * (c - a * shape) ** 2))
        if chi2 < best[0]:
            best = (chi2, s)
    dof = max(c.size - 2, 1)
    p = float(np.exp(log_chi2_sf(best[0], dof)))
    # The model's flux falls as exp(s x): in magnitudes the colour is -s / (0.4 ln 10).
    colour = -best[1] / (0.4 * np.log(10.0))
    return SpectrumTest(best[0], dof, p, float(colour))
