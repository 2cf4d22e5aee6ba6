"""Posterior sampling of companions with numpyro's NUTS (Hamiltonian Monte Carlo).

As in the paper's 'Interferometric Model Fitting': uniform priors on each companion's
(dRA, dDec) 150 mas wide and on its log10 flux ratio in each filter two decades wide, both
centred on the best fit; one multiplicative error scale ``sigma_scale`` per filter and
observable kind (uniform prior), which brings the reduced chi2 to about one and measures
how far the data scatter exceeds the propagated errors. Chains start at the best fit
and run in float64, in unconstrained coordinates (each box prior through a
sigmoid) with one compiled potential function.

Convergence is checked with the split R-hat and the effective sample size of every
parameter; poor values are reported (returned and emitted as :class:`PosteriorWarning`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from amigo.companions.fit import CompanionFitResult, block_residuals
from amigo.companions.observables import Dataset

#: Thresholds below which a chain is reported as poorly converged.
R_HAT_MAX = 1.05
ESS_MIN = 100.0


class PosteriorWarning(UserWarning):
    """The sampler's diagnostics suggest an unreliable posterior."""


@dataclass(frozen=True)
class Priors:
    """Half-widths and bounds of the uniform priors (paper: 150 mas, two decades)."""

    position_halfwidth_mas: float = 75.0
    log10_contrast_halfwidth: float = 1.0
    scale_bounds: tuple[float, float] = (0.01, 100.0)


@dataclass(frozen=True)
class Posterior:
    """Samples (chains concatenated) and diagnostics.

    ``samples``: ``"dra"``, ``"ddec"`` (n, K) mas; ``"log10c"`` (n, K, F); ``"scale"``
    (n, n_groups). ``r_hat`` and ``ess`` map each site to arrays of its element values.
    """

    samples: dict[str, np.ndarray]
    r_hat: dict[str, np.ndarray]
    ess: dict[str, np.ndarray]
    num_chains: int
    num_samples: int
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def r_hat_max(self) -> float:
        return float(max(np.nanmax(v) for v in self.r_hat.values()))

    @property
    def ess_min(self) -> float:
        return float(min(np.nanmin(v) for v in self.ess.values()))


#: Order of the sampled sites (each a uniform prior on a box).
SITES = ("dra", "ddec", "log10c", "scale")


def _to_box(z: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    """Unconstrained ``z`` -> ``lo + (hi - lo) sigmoid(z)``, inside the prior's box."""
    return lo + (hi - lo) * jax.nn.sigmoid(z)


def _to_box_numpy(z: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """:func:`_to_box` in NumPy float64 (``sigmoid(z) = (1 + tanh(z / 2)) / 2``)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return lo + (hi - lo) * 0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, np.float64)))


def _from_box(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_to_box` (NumPy)."""
    u = (np.asarray(x) - lo) / (hi - lo)
    return np.log(u) - np.log1p(-u)


@eqx.filter_jit
def _potential(z: dict, dataset: Dataset, bounds: dict, primary_diameter_mas: float):
    """Negative log posterior density in the unconstrained coordinates ``z``.

    Each site has a uniform prior on a box, sampled through ``x = lo + (hi - lo)
    sigmoid(z)``: the prior density in ``z`` is the Jacobian ``sigmoid(z) sigmoid(-z)``
    (up to a constant). The likelihood is Gaussian in the whitened residuals with one
    error scale per group: ``-chi2 / 2 - sum log(scale)`` over the observables.

    Compiled as one program (value and gradient): numpyro evaluates it eagerly while it
    initialises the chains, which op by op costs minutes of compilation on a small CPU.
    """
    x = {name: _to_box(z[name], *bounds[name]) for name in SITES}
    log_jacobian = sum(
        jnp.sum(jax.nn.log_sigmoid(z[name]) + jax.nn.log_sigmoid(-z[name])) for name in SITES
    )
    # The scene in the dataset's precision (float32 from sample_posterior), the sums of
    # squares in float64.
    dtype = dataset.blocks[0].design_tail.dtype
    offsets = jnp.stack([x["dra"], x["ddec"]], axis=-1).astype(dtype)
    contrasts = (10.0 ** x["log10c"]).astype(dtype)
    residuals = block_residuals(dataset, offsets, contrasts, primary_diameter_mas)
    loglike: float | jax.Array = 0.0
    for i, r in enumerate(residuals):
        s = x["scale"][dataset.group_index(i)]
        loglike = loglike - 0.5 * jnp.sum((r.astype(s.dtype) / s) ** 2) - jnp.sum(jnp.log(s))
    return -(loglike + log_jacobian)


def sample_posterior(
    dataset: Dataset,
    best: CompanionFitResult,
    initial_scales: np.ndarray,
    *,
    num_warmup: int = 500,
    num_samples: int = 1000,
    num_chains: int = 2,
    seed: int = 0,
    priors: Priors | None = None,
    primary_diameter_mas: float = 0.0,
    progress_bar: bool = False,
    chain_method: str = "sequential",
    single_precision: bool = True,
) -> Posterior:
    """Run NUTS from the best fit ``best`` and return samples with R-hat and ESS.

    Parameters
    ----------
    dataset
        Observables (any number of filters; companions share positions across filters).
    best
        Best fit to start from and centre the priors on.
    initial_scales
        (n_groups,) starting error scales (e.g. the maximum-likelihood estimates).
    num_warmup, num_samples, num_chains
        NUTS settings. Chains run one after the other by default: vectorised chains
        (``chain_method="vectorized"``) move in lockstep, each tree as deep as the
        deeper of the two, and their products with the observable matrices do not share
        the matrices' reads; on AB Dor's three filters (2-core CPU) two chains took 105
        s vectorised and 102 s one after the other, on one filter 41 and 23 s.
    single_precision
        Evaluate the residuals in float32 (:meth:`Dataset.single_precision`; the sums,
        the priors and the chains stay float64). The potential's value and gradient then
        cost half as much and the samples change within their Monte Carlo noise
        (docs/performance.md).
    """
    from numpyro.diagnostics import summary
    from numpyro.infer import MCMC, NUTS

    priors = priors or Priors()
    with jax.enable_x64(True):
        half = priors.position_halfwidth_mas
        centre_c = np.clip(best.log10_contrasts, -10.0, 0.0)
        hi_c = np.minimum(centre_c + priors.log10_contrast_halfwidth, 0.0)
        lo_c = hi_c - 2.0 * priors.log10_contrast_halfwidth
        lo_s, hi_s = priors.scale_bounds
        scales0 = np.clip(np.asarray(initial_scales, float), 1.01 * lo_s, 0.99 * hi_s)
        dra0, ddec0 = best.offsets_mas[:, 0], best.offsets_mas[:, 1]
        bounds = {
            "dra": (dra0 - half, dra0 + half),
            "ddec": (ddec0 - half, ddec0 + half),
            "log10c": (lo_c, hi_c),
            "scale": (np.full(dataset.n_groups, lo_s), np.full(dataset.n_groups, hi_s)),
        }
        start = {
            "dra": dra0,
            "ddec": ddec0,
            "log10c": np.clip(best.log10_contrasts, lo_c + 1e-6, hi_c - 1e-6),
            "scale": scales0,
        }
        z0 = {name: _from_box(start[name], *bounds[name]) for name in SITES}
        if num_chains > 1:
            z0 = {name: np.broadcast_to(v, (num_chains, *v.shape)) for name, v in z0.items()}
        init = {name: jnp.asarray(v) for name, v in z0.items()}
        diameter = float(primary_diameter_mas)
        evaluated = dataset.single_precision() if single_precision else dataset
        kernel = NUTS(
            potential_fn=lambda z: _potential(z, evaluated, bounds, diameter),
            dense_mass=True,
            target_accept_prob=0.85,
        )
        mcmc = MCMC(
            kernel,
            num_warmup=num_warmup,
            num_samples=num_samples,
            num_chains=num_chains,
            chain_method=chain_method,
            progress_bar=progress_bar,
        )
        mcmc.run(jax.random.PRNGKey(seed), init_params=init)
        z = mcmc.get_samples(group_by_chain=True)
        # Back to the physical box in NumPy (float64): eager JAX would compile each
        # operation of the transform on its own.
        grouped = {name: _to_box_numpy(np.asarray(z[name]), *bounds[name]) for name in SITES}
    stats = summary(grouped, group_by_chain=True)
    r_hat = {name: np.atleast_1d(np.asarray(s["r_hat"], float)) for name, s in stats.items()}
    ess = {name: np.atleast_1d(np.asarray(s["n_eff"], float)) for name, s in stats.items()}
    flat = {name: v.reshape(-1, *v.shape[2:]) for name, v in grouped.items()}
    messages = []
    worst_r = max(float(np.nanmax(v)) for v in r_hat.values())
    worst_ess = min(float(np.nanmin(v)) for v in ess.values())
    if not np.isfinite(worst_r) or worst_r > R_HAT_MAX:
        messages.append(
            f"NUTS: R-hat up to {worst_r:.3f} (> {R_HAT_MAX}): chains disagree; run more samples"
        )
    if not np.isfinite(worst_ess) or worst_ess < ESS_MIN:
        messages.append(
            f"NUTS: effective sample size down to {worst_ess:.0f} "
            f"(< {ESS_MIN:.0f}); errors are uncertain, run more samples"
        )
    for message in messages:
        warnings.warn(message, PosteriorWarning, stacklevel=2)
    return Posterior(
        samples=flat,
        r_hat=r_hat,
        ess=ess,
        num_chains=num_chains,
        num_samples=num_samples,
        warnings=tuple(messages),
    )
