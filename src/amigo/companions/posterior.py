"""Posterior sampling of companions with numpyro's NUTS (Hamiltonian Monte Carlo).

As in the paper's 'Interferometric Model Fitting': uniform priors on each companion's
(dRA, dDec) 150 mas wide and on its log10 flux ratio in each filter two decades wide, both
centred on the best fit; one multiplicative error scale ``sigma_scale`` per filter and
observable kind (uniform prior), which brings the reduced chi2 to about one and measures
how far the data scatter exceeds the propagated errors. Chains start at the best fit
(``init_to_value``) and run in float64.

Convergence is checked with the split R-hat and the effective sample size of every
parameter; poor values are reported (returned and emitted as :class:`PosteriorWarning`).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from amigo.companions.fit import FitResult, block_residuals
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


def _model(dataset: Dataset, bounds: dict, primary_diameter_mas: float):
    import numpyro
    import numpyro.distributions as dist

    dra = numpyro.sample("dra", dist.Uniform(*bounds["dra"]).to_event(1))
    ddec = numpyro.sample("ddec", dist.Uniform(*bounds["ddec"]).to_event(1))
    log10c = numpyro.sample("log10c", dist.Uniform(*bounds["log10c"]).to_event(2))
    scale = numpyro.sample("scale", dist.Uniform(*bounds["scale"]).to_event(1))
    offsets = jnp.stack([dra, ddec], axis=-1)
    residuals = block_residuals(dataset, offsets, 10.0**log10c, primary_diameter_mas)
    loglike = 0.0
    for i, r in enumerate(residuals):
        s = scale[dataset.group_index(i)]
        loglike = loglike - 0.5 * jnp.sum((r / s) ** 2) - jnp.sum(jnp.log(s))
    numpyro.factor("likelihood", loglike)


def sample_posterior(
    dataset: Dataset,
    best: FitResult,
    initial_scales: np.ndarray,
    *,
    num_warmup: int = 500,
    num_samples: int = 1000,
    num_chains: int = 2,
    seed: int = 0,
    priors: Priors | None = None,
    primary_diameter_mas: float = 0.0,
    progress_bar: bool = False,
    chain_method: str = "vectorized",
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
        NUTS settings; chains run one after the other (2 CPU cores are shared).
    """
    from numpyro.diagnostics import summary
    from numpyro.infer import MCMC, NUTS, init_to_value

    priors = priors or Priors()
    with jax.enable_x64(True):
        half = priors.position_halfwidth_mas
        centre_c = np.clip(best.log10_contrasts, -10.0, 0.0)
        hi_c = np.minimum(centre_c + priors.log10_contrast_halfwidth, 0.0)
        lo_c = hi_c - 2.0 * priors.log10_contrast_halfwidth
        lo_s, hi_s = priors.scale_bounds
        scales0 = np.clip(np.asarray(initial_scales, float), 1.01 * lo_s, 0.99 * hi_s)
        bounds = {
            "dra": (
                jnp.asarray(best.offsets_mas[:, 0] - half),
                jnp.asarray(best.offsets_mas[:, 0] + half),
            ),
            "ddec": (
                jnp.asarray(best.offsets_mas[:, 1] - half),
                jnp.asarray(best.offsets_mas[:, 1] + half),
            ),
            "log10c": (jnp.asarray(lo_c), jnp.asarray(hi_c)),
            "scale": (jnp.full(dataset.n_groups, lo_s), jnp.full(dataset.n_groups, hi_s)),
        }
        init = {
            "dra": jnp.asarray(best.offsets_mas[:, 0]),
            "ddec": jnp.asarray(best.offsets_mas[:, 1]),
            "log10c": jnp.asarray(np.clip(best.log10_contrasts, lo_c + 1e-6, hi_c - 1e-6)),
            "scale": jnp.asarray(scales0),
        }
        model = functools.partial(_model, primary_diameter_mas=float(primary_diameter_mas))
        kernel = NUTS(
            model,
            init_strategy=init_to_value(values=init),
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
        mcmc.run(jax.random.PRNGKey(seed), dataset, bounds)
        grouped = {name: np.asarray(v) for name, v in mcmc.get_samples(group_by_chain=True).items()}
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
