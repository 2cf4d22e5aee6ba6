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
   moves there by more than :data:`IWA_SIGMA` of its separation's errors is reported as
   such, never as a detection (:func:`inside_working_angle`).
3. **A physical spectrum.** A real companion's contrast changes smoothly across the AMI
   filters (3.8-4.8 um), but not necessarily monotonically: a cool companion's flux
   peaks between the methane band at 3.3 um and carbon monoxide's at 4.6 um, so F430M
   may be its brightest filter. The per-filter contrasts ``c_f`` (with their errors) are
   fitted by any non-negative spectrum ``m_f`` with at most one peak across the filters
   (rising to it and falling after it, in order of wavelength) whose colour between any
   two filters is at most :data:`MAX_RED_COLOUR_MAG_PER_UM` towards the red and
   :data:`MAX_BLUE_COLOUR_MAG_PER_UM` towards the blue (``m_f / m_g <= 10^(0.4 s |lambda_f
   - lambda_g|)``): for each place of the peak the constraints are linear, a
   convex cone, and the fit a least-squares projection on it. A chi2 with a tail
   probability below :data:`SPECTRUM_P_MIN` marks contrasts that no star, brown dwarf
   or planet has, such as dmag 25 in one filter and 0.2 in the next, or no flux in one
   filter between two that have it. (Until 2026-12-01 the spectrum had to be an
   exponential in wavelength, ``a exp(s (lambda - lambda_0))`` with the colour up to 3 mag
   per micron: HD 206893 c's own contrasts, 9.14 / 8.32 / 8.07 mag in F380M / F430M /
   F480M, are not one, and a simulated c found at 8.4 sigma was rejected.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, special, stats

#: Steepest companion-to-star colours admitted between two filters, in magnitudes per
#: micron of wavelength: brighter towards the red (a companion cooler than its star) and
#: fainter towards the red. Across [3.6]-[4.5] a late T dwarf against an A star is about
#: 2 mag per micron redder and the reddest Y dwarfs about 4 (WISE 0855-0714: [3.6] - [4.5]
#: = 3.5 mag over 0.9 um), steeper still locally between two neighbouring AMI filters on
#: the methane band's edge, hence 5. Two stars on the Rayleigh-Jeans tail have nearly
#: the same colours, and a companion fainter towards the red needs an absorption band
#: (carbon monoxide at 4.6 um in F480M: a fraction of a magnitude), hence 3, the bound
#: both ways had until 2026-12-01.
MAX_RED_COLOUR_MAG_PER_UM = 5.0
MAX_BLUE_COLOUR_MAG_PER_UM = 3.0
#: A candidate is inside the inner working angle, and not a detection, when its
#: separation is below it by more than this many of its errors. The separation is a
#: noisy estimate: a companion just outside is fitted inside in a good fraction of noise
#: draws (a 4-mag companion at 103 mas, 10 mas outside F480M's 93 mas, in 3 of 12;
#: docs/detect.md), and the data do not place it inside unless the separation's whole
#: 2-sigma interval is (to first order, a chi2 rise of 4 from the best fit to the inner
#: working angle). Until 2026-12-01: 0, the best fit alone.
IWA_SIGMA = 2.0
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


def inside_working_angle(sep_mas: float, sep_err_mas: float, iwa_mas: float) -> bool:
    """Whether a candidate at ``sep_mas +- sep_err_mas`` lies inside the inner working
    angle ``iwa_mas`` by more than :data:`IWA_SIGMA` of its errors (not a detection)."""
    return sep_mas + IWA_SIGMA * sep_err_mas < iwa_mas


@dataclass(frozen=True)
class SpectrumTest:
    """The fit of per-filter contrasts by a physical spectrum: its chi2, degrees of
    freedom, tail probability and the fitted spectrum's colour from the bluest filter to
    the reddest (mag per micron, positive: fainter in the red; 0 where it has no flux)."""

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
    """Test contrasts ``c_f +- sigma_f`` at ``wavelengths_um`` (F,) against every
    non-negative spectrum with at most one peak whose colours between any two filters are
    within :data:`MAX_RED_COLOUR_MAG_PER_UM` and :data:`MAX_BLUE_COLOUR_MAG_PER_UM`.

    For each filter that may hold the peak, the constraints (``m_f >= 0``, ``m_f <= R_fg
    m_g`` with ``R_fg`` the colour bound's flux ratio, and the order of the ``m`` on each
    side of the peak) are linear, and the best spectrum is a weighted least-squares
    projection on a convex cone (SLSQP, started from a flat spectrum, which every cone
    holds); the best over the peaks is taken. Degrees of freedom: one. The distance to a
    cone is distributed as a mixture of chi2 with 0 to F degrees of freedom; a real
    companion's spectrum lies inside a cone, where contrasts within their errors need no
    constraint at all, and a rejection needs a constraint that binds.
    """
    c = np.asarray(contrasts, dtype=float)
    sigma = np.asarray(errors, dtype=float)
    lam = np.asarray(wavelengths_um, dtype=float)
    if c.size < 2:
        return SpectrumTest(0.0, 0, 1.0, 0.0)
    order = np.argsort(lam)
    # In units of the largest error (SLSQP's tolerances are absolute), by wavelength.
    unit = float(np.max(sigma))
    y, w, lam = c[order] / unit, (unit / sigma[order]) ** 2, lam[order]

    def chi2(m: np.ndarray) -> float:
        return float(np.sum(w * (y - m) ** 2))

    flat = np.full(c.size, max(float(np.sum(w * y) / np.sum(w)), 0.0))
    best = flat
    for peak in range(c.size):
        rows = _cone_rows(lam, peak)
        result = optimize.minimize(
            chi2,
            flat,
            jac=lambda m: -2.0 * w * (y - m),
            method="SLSQP",
            constraints=[
                {"type": "ineq", "fun": lambda m, a=rows: a @ m, "jac": lambda m, a=rows: a}
            ],
            options={"ftol": 1e-12, "maxiter": 200},
        )
        # SLSQP may end a hair outside its cone: such an end is not taken.
        m = np.maximum(result.x, 0.0)
        inside = np.all(rows @ m >= -1e-9 * max(1.0, float(np.max(m))))
        if inside and chi2(m) < chi2(best):
            best = m
    value = chi2(best)
    p = float(np.exp(log_chi2_sf(value, 1)))
    span = float(lam[-1] - lam[0])
    ends = best[[0, -1]]
    colour = float(-2.5 * np.log10(ends[1] / ends[0]) / span) if np.all(ends > 0) else 0.0
    return SpectrumTest(value, 1, p, colour)


def _cone_rows(wavelengths_um: np.ndarray, peak: int) -> np.ndarray:
    """Rows ``A`` of the cone ``A m >= 0`` of spectra at ``wavelengths_um`` (F,
    ascending) peaking in filter ``peak``: every colour within the bound, the flux rising
    up to the peak and falling after it, and no negative flux."""
    n = wavelengths_um.size
    gap = wavelengths_um[:, None] - wavelengths_um[None, :]  # lambda_f - lambda_g
    # Largest m_f / m_g admitted: f redder than g (gap > 0), the companion brighter
    # towards the red by at most the red bound; bluer, by at most the blue bound.
    slope = np.where(gap > 0, MAX_RED_COLOUR_MAG_PER_UM, MAX_BLUE_COLOUR_MAG_PER_UM)
    ratio = 10.0 ** (0.4 * slope * np.abs(gap))
    rows = []
    for f in range(n):
        for g in range(n):
            if f != g:
                row = np.zeros(n)
                row[f], row[g] = -1.0, ratio[f, g]  # R_fg m_g - m_f >= 0
                rows.append(row)
    for f in range(n - 1):
        row = np.zeros(n)
        # Before the peak m_{f+1} - m_f >= 0; from it on m_f - m_{f+1} >= 0.
        row[f], row[f + 1] = (-1.0, 1.0) if f < peak else (1.0, -1.0)
        rows.append(row)
    return np.vstack([*rows, np.eye(n)])
