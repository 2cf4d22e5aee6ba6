"""Kernel projection, calibration and DISCOs: from fitted latent visibilities to observables.

The paper's sections "Kernel Amplitudes & Phases" and "Visibility reduction", in plain
float64 NumPy linear algebra (nothing here is differentiated).

Notation (per filter)
---------------------
``x = [a, p]``
    Latent log-amplitudes ``a`` (``m_a``) and phases ``p`` (``m_p``) of one target, with
    covariance ``C`` (from the Hessian of the log-likelihood, :mod:`amigo.fitting.filter_fit`).
``G = [G_a; G_p]``
    (``m_a + m_p``, ``n_nuisance``) Jacobian of the latent visibilities with respect to
    the instrumental nuisances (70 Zernikes, flux, spectral slope, defocus) at the
    calibrator's state: how much a fit would move ``x`` to absorb a small nuisance error.
``K_a``, ``K_p``
    Kernel projectors: rows spanning the left null spaces of ``G_a`` and ``G_p``
    (``K G = 0``), from the singular value decomposition. The amplitude and phase parts
    are nulled separately so that every observable is an amplitude or a phase one (the
    paper's convention): ``K_a a`` does not change when a nuisance does, to first order.
Calibration
    ``k = K (x_sci - x_cal)`` (subtraction of log visibilities = division of complex
    visibilities), covariance ``K (C_sci + C_cal) K^T``.
DISCOs
    ``d = T k`` with ``T`` decorrelating: the amplitude kernel is rotated into the
    eigenbasis of its covariance; the phase kernel is first conditioned on the amplitudes
    (``k_p - C_pa C_aa^-1 k_a``, which removes any amplitude-phase correlation: exact
    independence while each observable stays mostly amplitude or phase) and then rotated
    into the eigenbasis of its conditional covariance. ``d`` has a diagonal covariance
    ``diag(sigma^2)``.
The DISCO matrix
    Every step is linear, so ``D = T K B^T`` maps log-visibilities at the knots of the uv
    grid (``[log|V|, arg V]`` at the half-plane knots, with ``B`` the latent basis) to
    DISCOs: a model's ``D v`` is directly comparable with ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from amigo.errors import NumericalFailure, numerical, require_finite

#: Singular values of the nuisance Jacobian above this fraction of the largest one count
#: as instrumental directions (nulled). The paper's research code used ~1e-12; we use a
#: slightly larger floor because the Jacobians come from float32 images.
DEFAULT_RCOND = 1e-9


def kernel_projector(jacobian: np.ndarray, rcond: float = DEFAULT_RCOND) -> np.ndarray:
    """Orthonormal rows spanning the left null space of ``jacobian``.

    Parameters
    ----------
    jacobian
        (m, n) sensitivity of ``m`` observables to ``n`` nuisance parameters.
    rcond
        Relative singular-value threshold for the rank.

    Returns
    -------
    (m - rank, m) matrix ``K`` with ``K @ K.T = I`` and ``K @ jacobian ~ 0``.
    """
    jacobian = np.asarray(jacobian, dtype=float)
    m = jacobian.shape[0]
    if jacobian.size == 0:
        return np.eye(m)
    u, s, _ = np.linalg.svd(jacobian, full_matrices=True)
    rank = int(np.count_nonzero(s > rcond * s[0])) if s.size and s[0] > 0 else 0
    return u[:, rank:].T


def nuisance_regression(hessian: np.ndarray, cross: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """Latent response to nuisances: ``G = H^-1 (J_x^T W J_theta)`` (least squares).

    A fit that holds a nuisance ``theta`` wrong by ``d theta`` moves the latent
    visibilities by ``G d theta`` to first order: the weighted least-squares projection of
    the image change ``J_theta d theta`` onto the image changes ``J_x`` the latent
    visibilities can make.

    Parameters
    ----------
    hessian
        (m, m) ``J_x^T W J_x``, summed over the exposures that define the state.
    cross
        (m, n) ``J_x^T W J_theta``, summed likewise.
    """
    return np.linalg.lstsq(hessian, cross, rcond=rcond)[0]


def covariance_from_hessian(hessian: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi-)definite Hessian, by eigendecomposition.

    Directions with eigenvalues below 1e-12 of the largest (not constrained by the data)
    get a variance of ``1e12 / largest`` instead of infinity, so that downstream
    projections stay finite; they are reported by :func:`hessian_condition`.
    """
    h = 0.5 * (hessian + hessian.T)
    evals, evecs = np.linalg.eigh(h)
    floor = 1e-12 * evals.max()
    inv = 1.0 / np.maximum(evals, floor)
    return (evecs * inv) @ evecs.T


def hessian_condition(hessian: np.ndarray) -> float:
    """Ratio of the largest to the smallest eigenvalue (``inf`` if singular)."""
    evals = np.linalg.eigvalsh(0.5 * (hessian + hessian.T))
    return float(evals.max() / evals.min()) if evals.min() > 0 else float("inf")


@dataclass(frozen=True)
class Kernel:
    """Kernel projectors of one filter.

    Attributes
    ----------
    amp, phase
        (k_a, m_a), (k_p, m_p) orthonormal rows (see :func:`kernel_projector`).
    n_nuisance
        Number of nuisance parameters nulled over.
    singular_values_amp, singular_values_phase
        Singular values of the two Jacobians (descending), for diagnostics.
    """

    amp: np.ndarray
    phase: np.ndarray
    n_nuisance: int
    singular_values_amp: np.ndarray
    singular_values_phase: np.ndarray

    @property
    def matrix(self) -> np.ndarray:
        """(k_a + k_p, m_a + m_p) block-diagonal projector acting on ``[a, p]``."""
        ka, ma = self.amp.shape
        kp, mp = self.phase.shape
        out = np.zeros((ka + kp, ma + mp))
        out[:ka, :ma] = self.amp
        out[ka:, ma:] = self.phase
        return out

    @property
    def n_amp(self) -> int:
        return int(self.amp.shape[0])


def envelope_knots(knots_m: np.ndarray, baselines_m: np.ndarray, reach_m: float) -> np.ndarray:
    """Knots the mask's fringes do not reach: (n_used,) booleans.

    A knot at ``b`` is an *envelope knot* when it lies within ``reach_m`` of the origin
    and farther than ``reach_m`` from every baseline ``B`` and its mirror ``-B``. With ``reach_m`` the holes' flat-to-flat width,
    the half-width of a baseline's OTF splodge across its flats, such a knot lies where
    the OTF is only the holes' common autocorrelation (the zero-baseline splodge): the
    image sees its visibility only through the shape of the single-hole envelope, which
    the pixels' own response (flat, intra-pixel response, charge migration, jitter) also
    shapes. For the 51 x 51 grid 0.259 m apart and NIRISS's 0.8 m holes (shortest
    baseline 1.32 m) these are the 8 knots within 0.58 m of the origin.

    Parameters
    ----------
    knots_m
        (n_used, 2) knot baselines (m), the basis's free half-plane knots.
    baselines_m
        (n_b, 2) mask baselines (m), same frame.
    reach_m
        Distance (m) from a baseline within which its fringes reach.
    """
    b = np.asarray(baselines_m, dtype=float)
    b = np.concatenate([b, -b])
    k = np.asarray(knots_m, dtype=float)
    distance = np.linalg.norm(k[:, None, :] - b[None], axis=-1).min(axis=1)
    return (np.linalg.norm(k, axis=1) < reach_m) & (distance > reach_m)


def knot_nuisance(latent_from_knots: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(m_a + m_p, 2 n) latent response to the log-amplitude and the phase of each of the
    ``n`` selected knots (``knots``: (n_used,) booleans), columns of unit norm or less:
    nuisance directions for :func:`build_kernel` that make the observables blind to
    those knots' visibilities."""
    index = np.flatnonzero(knots)
    n_used = latent_from_knots.shape[1] // 2
    return np.asarray(latent_from_knots, float)[:, np.concatenate([index, n_used + index])]


def build_kernel(nuisance_jacobian: np.ndarray, n_amp: int, rcond: float = DEFAULT_RCOND) -> Kernel:
    """Kernel projectors from the (m_a + m_p, n) latent nuisance Jacobian ``G``.

    The first ``n_amp`` rows of ``G`` are the amplitude latents, the rest the phases.
    """
    g = np.asarray(nuisance_jacobian, dtype=float)
    ga, gp = g[:n_amp], g[n_amp:]
    return Kernel(
        amp=kernel_projector(ga, rcond),
        phase=kernel_projector(gp, rcond),
        n_nuisance=g.shape[1],
        singular_values_amp=np.linalg.svd(ga, compute_uv=False) if ga.size else np.zeros(0),
        singular_values_phase=np.linalg.svd(gp, compute_uv=False) if gp.size else np.zeros(0),
    )


def combine(
    values: list[np.ndarray], covariances: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance weighted mean of several estimates of the same vector.

    Used to combine several calibrators (each fitted with its own visibilities) into one
    reference. Returns ``(mean, covariance)``.
    """
    if len(values) == 1:
        return np.asarray(values[0], float), np.asarray(covariances[0], float)
    precisions = [np.linalg.inv(c) for c in covariances]
    total = np.sum(precisions, axis=0)
    cov = np.linalg.inv(total)
    mean = cov @ np.sum([p @ v for p, v in zip(precisions, values, strict=True)], axis=0)
    return mean, 0.5 * (cov + cov.T)


def decorrelation(covariance: np.ndarray, n_amp: int) -> tuple[np.ndarray, np.ndarray]:
    """The DISCO transform ``T`` and variances for a kernel covariance (see module notes).

    Parameters
    ----------
    covariance
        (k, k) covariance of ``[k_a, k_p]`` (first ``n_amp`` entries amplitudes).

    Returns
    -------
    transform
        (k, k) ``T``: ``d = T @ [k_a, k_p]`` has a diagonal covariance.
    variances
        (k,) the diagonal, amplitudes first, each block in decreasing order of variance
        reversed (best-measured first).
    """
    c = 0.5 * (covariance + covariance.T)
    na = n_amp
    caa, cap, cpp = c[:na, :na], c[:na, na:], c[na:, na:]
    # Amplitudes: eigenbasis of their covariance.
    va, ea = np.linalg.eigh(caa)
    # Phases conditioned on amplitudes: k_p' = k_p - C_pa C_aa^-1 k_a (least squares: a
    # C_aa without inverse, from a covariance that is not positive definite, conditions on
    # the amplitude directions that have variance; the others are left out in discos()).
    condition = np.linalg.lstsq(caa, cap, rcond=None)[0].T if na else np.zeros((c.shape[0] - na, 0))
    cond_cov = cpp - condition @ cap
    vp, ep = np.linalg.eigh(0.5 * (cond_cov + cond_cov.T))
    k = c.shape[0]
    transform = np.zeros((k, k))
    transform[:na, :na] = ea.T
    transform[na:, na:] = ep.T
    transform[na:, :na] = -ep.T @ condition
    return transform, np.concatenate([va, vp])


@dataclass(frozen=True)
class Discos:
    """Calibrated, statistically independent observables of one target in one filter.

    Attributes
    ----------
    values, errors
        (n,) DISCOs and 1-sigma errors.
    kinds
        (n,) ``"amplitude"`` or ``"phase"``.
    matrix
        (n, 2 n_uv) ``D``: ``[log|V|, arg V]`` at the uv knots -> DISCOs.
    latent_matrix
        (n, m_a + m_p) ``T K``: calibrated latent visibilities -> DISCOs.
    kernel
        The :class:`Kernel` used.
    dropped
        Kernel directions left out because their variance is not positive (a
        covariance that is not positive definite: no DISCO can be formed there).
    """

    values: np.ndarray
    errors: np.ndarray
    kinds: tuple[str, ...]
    matrix: np.ndarray
    latent_matrix: np.ndarray
    kernel: Kernel
    dropped: int = 0

    def chi2(self, model_log_vis: np.ndarray) -> float:
        """``sum ((d - D v) / sigma)^2`` for a model's ``[log|V|, arg V]`` at the knots."""
        r = (self.values - self.matrix @ model_log_vis) / self.errors
        return float(r @ r)


def row_signs(matrix: np.ndarray) -> np.ndarray:
    """(n,) +-1 that make the largest-magnitude entry of each row of ``matrix`` positive.

    The DISCOs' convention: an eigenvector's sign is arbitrary, and without one a change
    in the last bits of a fit (another machine, another release) could flip a DISCO and
    its row together, products equivalent but not comparable value by value.
    """
    matrix = np.asarray(matrix)
    if matrix.size == 0:
        return np.ones(matrix.shape[0])
    largest = matrix[np.arange(matrix.shape[0]), np.argmax(np.abs(matrix), axis=1)]
    return np.where(largest < 0, -1.0, 1.0)


def discos(
    science: np.ndarray,
    science_cov: np.ndarray,
    calibrator: np.ndarray,
    calibrator_cov: np.ndarray,
    kernel: Kernel,
    latent_to_knots: np.ndarray,
) -> Discos:
    """Calibrate and decorrelate latent visibilities into DISCOs.

    Parameters
    ----------
    science, calibrator
        (m_a + m_p,) latent ``[a, p]`` of the science target and of the calibrator
        (combined with :func:`combine` if several).
    science_cov, calibrator_cov
        Their (m, m) covariances.
    kernel
        From :func:`build_kernel`.
    latent_to_knots
        (m, 2 n_uv) ``B^T``: knot log-visibilities -> latents (the transpose of the
        orthonormal basis, restricted to the listed knots).

    Raises
    ------
    NumericalFailure
        Values or covariance not finite, or no direction of positive variance. Directions
        whose variance is not positive (a covariance that is not positive definite) are
        left out and counted in :attr:`Discos.dropped`: a zero error would give them
        infinite weight downstream.
    """
    k = kernel.matrix
    value = k @ (np.asarray(science) - np.asarray(calibrator))
    cov = k @ (np.asarray(science_cov) + np.asarray(calibrator_cov)) @ k.T
    require_finite("DISCOs", "kernel phases and amplitudes", value)
    require_finite("DISCOs", "kernel covariance entries", cov)
    with numerical("DISCO decorrelation"):
        transform, variances = decorrelation(cov, kernel.n_amp)
    # The sign convention on the rows as the calvis file stores them (knot space).
    transform = transform * row_signs(transform @ k @ latent_to_knots)[:, None]
    kinds = np.array(["amplitude"] * kernel.n_amp + ["phase"] * (k.shape[0] - kernel.n_amp))
    keep = np.isfinite(variances) & (variances > 0.0)
    if not keep.any():
        raise NumericalFailure("DISCOs", "the kernel covariance has no positive variance")
    latent_matrix = transform[keep] @ k
    return Discos(
        values=(transform @ value)[keep],
        errors=np.sqrt(variances[keep]),
        kinds=tuple(str(kind) for kind in kinds[keep]),
        matrix=latent_matrix @ latent_to_knots,
        latent_matrix=latent_matrix,
        kernel=kernel,
        dropped=int(np.sum(~keep)),
    )
