"""Posterior sampling of companions with numpyro's NUTS (Hamiltonian Monte Carlo).

As in the paper's 'Interferometric Model Fitting': uniform priors on each companion's
(dRA, dDec) 150 mas wide and on its log10 flux ratio in each filter two decades wide, both
centred on the best fit; one multiplicative error scale ``sigma_scale`` per filter and
observable kind (uniform prior), which brings the reduced chi2 to about one and measures
how far the data scatter exceeds the propagated errors. Chains start at the best fit
and run in float64, in unconstrained coordinates (each box prior through a
sigmoid) with one compiled potential function, whose observables are arguments of the
compiled sampling loops (so one program serves every target of the same shapes). The
warm-up starts from Laplace's covariance as the inverse mass matrix; sampling stops once
the means (numpyro's ``n_eff``) and the error percentiles have :data:`ESS_TARGET`
effective samples.

Convergence is checked with the split R-hat and the effective sample size of every
parameter; poor values are reported (returned and emitted as :class:`PosteriorWarning`).
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from amigo import programs
from amigo.companions.fit import CompanionFitResult, block_residuals
from amigo.companions.observables import Dataset, program_view

#: Thresholds below which a chain is reported as poorly converged.
R_HAT_MAX = 1.05
ESS_MIN = 100.0

#: Sampling stops early once every parameter has this effective sample size (chains
#: together) for its mean (numpyro's ``n_eff``, the bulk ESS) *and* for the two
#: percentiles that give its error
#: (:data:`ERROR_PERCENTILES`), with R-hat at most :data:`R_HAT_STOP`: the thresholds
#: Vehtari et al. (2021, Bayesian Analysis 16, 667) recommend before a posterior's
#: quantiles are reported. At 400 the Monte Carlo error of a Gaussian posterior's mean
#: is 0.05 of its standard deviation, that of each percentile 0.08, that of the error
#: (half their difference) about 5 % of itself. The percentiles' ESS is the one that
#: binds: NUTS's draws are anti-correlated in the mean, so the mean's ESS can exceed
#: the number of draws while the tails' is a third of it.
ESS_TARGET = 400
R_HAT_STOP = 1.01

#: The percentiles whose half-difference is a reported error (one sigma of a Gaussian).
ERROR_PERCENTILES = (15.865, 84.135)

#: Warm-up steps per chain when Laplace's covariance is the mass matrix: the warm-up
#: then tunes the step size alone (dual averaging). Measured on AB Dor's three filters
#: (docs/performance.md, a tenth session): that mass matrix gives as few leapfrogs per
#: sample as one adapted over 500 warm-up steps (6.9 per sample in either) and the same
#: effective sample size per draw; 75 warm-up steps were as good as 150, and a mass
#: matrix adapted within 150 steps took 10.5 leapfrogs per sample.
WARMUP_LAPLACE = 150
#: Warm-up steps per chain when the mass matrix is adapted (Stan's windowed schedule,
#: numpyro's default): 75 steps of step size alone, windows of 25, 50, 100 and 200, 50
#: to finish.
WARMUP_ADAPTIVE = 500
#: NUTS's target acceptance probability during the warm-up's step-size tuning.
TARGET_ACCEPT = 0.85

#: Samples per chain drawn with the warm-up before the first check of the stopping rule
#: (at most; the requested number is split into equal chunks).
CHUNK = 250
#: Samples per chain drawn between the later checks, as a fraction of :data:`CHUNK`
#: (every continuation the same size, so one compiled loop serves them all). Half: on
#: AB Dor's four posteriors the error percentiles' ESS after the first chunk was 251-398
#: of the 400 asked, after a second full chunk 674-783 (docs/performance.md, an eleventh
#: session): a whole chunk more drew up to twice what the rule needed.
CONTINUATION = 0.5


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
    ``num_warmup`` is the warm-up per chain and ``mass_matrix`` how its mass matrix was
    made: ``"laplace"`` (Laplace's covariance, kept) or ``"adapted"`` (by the warm-up).
    """

    samples: dict[str, np.ndarray]
    r_hat: dict[str, np.ndarray]
    ess: dict[str, np.ndarray]
    num_chains: int
    num_samples: int
    warnings: tuple[str, ...] = field(default_factory=tuple)
    ess_percentiles: dict[str, np.ndarray] = field(default_factory=dict)
    num_warmup: int = 0
    mass_matrix: str = ""

    @property
    def r_hat_max(self) -> float:
        return float(max(np.nanmax(v) for v in self.r_hat.values()))

    @property
    def ess_min(self) -> float:
        return float(min(np.nanmin(v) for v in self.ess.values()))

    @property
    def ess_percentiles_min(self) -> float:
        """The smallest effective sample size of the error percentiles (NaN: none)."""
        if not self.ess_percentiles:
            return float("nan")
        return float(min(np.nanmin(v) for v in self.ess_percentiles.values()))


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
def _potential(
    z: dict,
    dataset: Dataset,
    bounds: dict,
    primary_diameter_mas: float,
    groups: tuple[jax.Array, ...] | None = None,
):
    """Negative log posterior density in the unconstrained coordinates ``z``.

    Each site has a uniform prior on a box, sampled through ``x = lo + (hi - lo)
    sigmoid(z)``: the prior density in ``z`` is the Jacobian ``sigmoid(z) sigmoid(-z)``
    (up to a constant). The likelihood is Gaussian in the whitened residuals with one
    error scale per group: ``-chi2 / 2 - sum log(scale)`` over the observables.
    ``groups``: each block's group index per observable (a
    :class:`~amigo.companions.observables.ProgramView`'s, whose
    padded rows point at an inert slot of scale 1); ``None``: the dataset's own.

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
    if groups is None:
        groups = tuple(jnp.asarray(dataset.group_index(i)) for i in range(len(residuals)))
    # The last slot, scale 1, is padded rows' (residual 0): they add nothing.
    scales = jnp.concatenate([x["scale"], jnp.ones((1,), x["scale"].dtype)])
    loglike: float | jax.Array = 0.0
    for i, r in enumerate(residuals):
        s = scales[groups[i]]
        loglike = loglike - 0.5 * jnp.sum((r.astype(s.dtype) / s) ** 2) - jnp.sum(jnp.log(s))
    return -(loglike + log_jacobian)


@programs.jit
def _nuts_draws(
    start: Any,
    dataset: Dataset,
    groups: tuple[jax.Array, ...],
    bounds: dict,
    primary_diameter_mas: float,
    inverse_mass: jax.Array | None,
    num_warmup: int,
    num_draws: int,
) -> tuple[dict, Any]:
    """One chain's NUTS draws: ``(draws, state)``, each site's draws (num_draws, ...) in
    the unconstrained coordinates and the sampler's last state.

    ``start`` is either ``(z, rng_key)``, a new chain (``num_warmup`` steps of warm-up,
    tuning the step size and, where ``inverse_mass`` is ``None``, a dense mass matrix in
    Stan's windows, then the draws), or the ``HMCState`` a previous call returned: the
    same chain continued, its adapted step size and mass matrix kept (``num_warmup`` is
    then the warm-up the chain began with, which the sampler's state counts against).

    numpyro's functional NUTS (``numpyro.infer.hmc.hmc``) in one program with the
    observables and the boxes as arguments (a potential that closed over them would put
    every matrix into the program as a constant, 21-85 MB a program, and a new target
    would compile anew): the program is the same for every chain and target of these
    shapes, and kept on disk (:mod:`amigo.programs`); the observables come padded to
    bucket sizes (:func:`~amigo.companions.observables.program_view`) so that another
    target's files usually have these shapes too; numpyro's ``MCMC``
    lowered a sampling loop of its own for every chain and every run (16 per AB Dor
    detection, 8 s of a warm run on a 2-core CPU).
    """
    from numpyro.infer.hmc import HMCState, hmc

    init_kernel, sample_kernel = hmc(
        potential_fn=lambda z: _potential(z, dataset, bounds, primary_diameter_mas, groups),
        algo="NUTS",
    )
    continuing = isinstance(start, HMCState)
    z0, key = (start.z, start.rng_key) if continuing else start
    # Sets the sampler's settings (numpyro keeps them in the closure of sample_kernel);
    # a continued chain then takes its own state instead of the new one.
    state = init_kernel(
        z0,
        num_warmup,
        inverse_mass_matrix=inverse_mass,
        adapt_mass_matrix=inverse_mass is None,
        dense_mass=True,
        target_accept_prob=TARGET_ACCEPT,
        rng_key=key,
    )
    if continuing:
        state = start
    else:
        state = jax.lax.fori_loop(0, num_warmup, lambda _, s: sample_kernel(s), state)

    def draw(s: Any, _: Any) -> tuple[Any, dict]:
        s = sample_kernel(s)
        return s, s.z

    state, draws = jax.lax.scan(draw, state, None, length=num_draws)
    return draws, state


def sample_posterior(
    dataset: Dataset,
    best: CompanionFitResult,
    initial_scales: np.ndarray,
    *,
    num_warmup: int | None = None,
    num_samples: int = 1000,
    num_chains: int = 2,
    seed: int = 0,
    priors: Priors | None = None,
    primary_diameter_mas: float = 0.0,
    single_precision: bool = True,
    ess_target: float = ESS_TARGET,
    laplace_mass: bool = True,
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
        NUTS settings; ``num_samples`` per chain is the most drawn (see ``ess_target``),
        ``num_warmup`` per chain defaults to :data:`WARMUP_LAPLACE` where Laplace's
        covariance is the mass matrix, else :data:`WARMUP_ADAPTIVE`.
        Chains run side by side in threads (:func:`amigo.programs.side_by_side`; on a
        2-core CPU AB Dor's joint posterior took 4.2-4.3 s instead of 6.5 s, one
        filter's 1.1 s instead of 2.2 s), each through the same compiled program. Not
        vectorised: vectorised chains move in lockstep, each tree as deep as the deeper
        of the two, and their products with the observable matrices do not share the
        matrices' reads (on AB Dor's three filters, 2-core CPU, with numpyro's
        ``MCMC``: two chains took 105 s vectorised and 102 s one after the other, on
        one filter 41 and 23 s).
    single_precision
        Evaluate the residuals in float32 (:meth:`Dataset.single_precision`; the sums,
        the priors and the chains stay float64). The potential's value and gradient then
        cost half as much and the samples change within their Monte Carlo noise
        (docs/performance.md).
    ess_target
        Stop drawing once every parameter's effective sample size, for its mean and
        for its error's percentiles, reaches this and its R-hat is at most
        :data:`R_HAT_STOP`, checked after the first :data:`CHUNK` samples per chain and
        then every :data:`CONTINUATION` of a chunk (at most); 0
        draws all ``num_samples``. The posterior's ``num_samples`` is the number drawn
        per chain (:data:`ESS_TARGET`: what the default of 400 bounds).
    laplace_mass
        Use Laplace's covariance as the inverse mass matrix (:func:`_laplace_inverse_mass`;
        default): the warm-up then tunes the step size only. Otherwise (or where that
        matrix is not positive definite) the warm-up starts from numpyro's identity and
        adapts a dense mass matrix in Stan's windows.
    """
    from numpyro.diagnostics import summary

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
        z0 = {name: jnp.asarray(_from_box(start[name], *bounds[name])) for name in SITES}
        diameter = float(primary_diameter_mas)
        evaluated = program_view(dataset)  # the search's view, made once
        if single_precision:
            evaluated = replace(evaluated, dataset=evaluated.dataset.single_precision())
        boxes = jax.tree.map(jnp.asarray, bounds)
        inverse_mass = (
            _laplace_inverse_mass(dataset, best, scales0, start, bounds) if laplace_mass else None
        )
        if num_warmup is None:
            num_warmup = WARMUP_ADAPTIVE if inverse_mass is None else WARMUP_LAPLACE
        mass = None if inverse_mass is None else jnp.asarray(inverse_mass)
        keys = jax.random.split(jax.random.PRNGKey(seed), num_chains)
        # On an accelerator the chains may run on the host (programs.latency_device):
        # their inputs are committed there, and their programs made for it.
        device = programs.latency_device()
        inputs = programs.on_device((evaluated.dataset, evaluated.groups, boxes, mass), device)

        def run(starts: list, n: int) -> tuple[dict[str, np.ndarray], list]:
            """Every chain's next ``n`` draws from ``starts``: (chains, n, ...) per site in
            the physical box, and the chains' last states."""
            dataset_, groups_, boxes_, mass_ = inputs
            common = (dataset_, groups_, boxes_, diameter, mass_, num_warmup, n)
            # Side by side in threads: each chain alone leaves a 2-core CPU a third idle.
            with contextlib.nullcontext() if device is None else jax.default_device(device):
                results = programs.side_by_side(
                    lambda start: _nuts_draws(start, *common), programs.on_device(starts, device)
                )
            per_chain, ends = [r[0] for r in results], [r[1] for r in results]
            boxed = {
                name: _to_box_numpy(
                    np.stack([np.asarray(d[name]) for d in per_chain]), *bounds[name]
                )
                for name in SITES
            }
            return boxed, ends

        # The first draws with the warm-up, then equal continuations (CONTINUATION): one
        # compiled sampling loop serves every continuation.
        n_chunks = -(-num_samples // CHUNK) if ess_target > 0 else 1
        chunk = -(-num_samples // n_chunks)
        first, states = run([(z0, key) for key in keys], chunk)
        parts = [first]
        more = max(1, int(np.ceil(CONTINUATION * chunk)))
        while True:
            grouped = {
                name: np.concatenate([p[name] for p in parts], axis=1)[:, :num_samples]
                for name in SITES
            }
            stats = summary(grouped, group_by_chain=True)
            tails = {name: _percentile_ess(v) for name, v in grouped.items()}
            drawn = grouped["dra"].shape[1]
            if drawn >= num_samples or _converged(stats, tails, ess_target):
                break
            # Continue every chain from its last state, adapted step size and mass matrix
            # kept (no new warm-up): the same chain as one long run.
            part, states = run(states, more)
            parts.append(part)
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
        num_samples=drawn,
        warnings=tuple(messages),
        ess_percentiles=tails,
        num_warmup=num_warmup,
        mass_matrix="adapted" if inverse_mass is None else "laplace",
    )


def _laplace_inverse_mass(
    dataset: Dataset, best: CompanionFitResult, scales: np.ndarray, start: dict, bounds: dict
) -> np.ndarray | None:
    """The posterior's covariance in the sampled coordinates ``z`` by Laplace's
    approximation at the start: NUTS's first inverse mass matrix, which its warm-up then
    adapts (identity otherwise: numpyro's default).

    The companions' block is the least-squares covariance of ``best`` (``[offsets.ravel(),
    log10c.ravel()]``); an error scale ``s`` of a group of ``N`` observables has variance
    ``s^2 / (2 N)`` (the curvature of ``-chi2 / (2 s^2) - N log s`` at its maximum) and is
    uncorrelated with them there. Each is carried to ``z`` by ``dz/dx = (hi - lo) / ((x -
    lo)(hi - x))``, in the order numpyro flattens the sites (sorted names: ddec, dra,
    log10c, scale). ``None`` where that matrix is not finite and positive definite.
    """
    k, f = best.log10_contrasts.shape
    # Positions of each flattened site's entries in [offsets.ravel(), log10c.ravel()].
    where = {
        "dra": 2 * np.arange(k),
        "ddec": 2 * np.arange(k) + 1,
        "log10c": 2 * k + np.arange(k * f),
    }
    counts = dataset.group_counts()
    n_fit = 2 * k + k * f
    order = sorted(SITES)
    index = np.concatenate([where[name] for name in order if name != "scale"])
    n = n_fit + dataset.n_groups
    covariance = np.zeros((n, n))
    covariance[:n_fit, :n_fit] = np.asarray(best.covariance)[np.ix_(index, index)]
    scales = np.asarray(scales, float)
    covariance[n_fit:, n_fit:] = np.diag(scales**2 / (2.0 * np.maximum(counts, 1.0)))
    x = np.concatenate([np.ravel(start[name]) for name in order])
    lo = np.concatenate(
        [np.ravel(np.broadcast_to(bounds[name][0], np.shape(start[name]))) for name in order]
    )
    hi = np.concatenate(
        [np.ravel(np.broadcast_to(bounds[name][1], np.shape(start[name]))) for name in order]
    )
    jacobian = (hi - lo) / ((x - lo) * (hi - x))
    inverse_mass = covariance * np.outer(jacobian, jacobian)
    try:
        np.linalg.cholesky(inverse_mass)
    except np.linalg.LinAlgError:
        return None
    return inverse_mass if np.all(np.isfinite(inverse_mass)) else None


def _percentile_ess(x: np.ndarray) -> np.ndarray:
    """Effective sample size of the error percentiles of every element of ``x`` (chains,
    draws, ...): for each, the smaller of the ESS of the indicators ``x <= q`` at the
    two :data:`ERROR_PERCENTILES` ``q`` (the quantile ESS of Vehtari et al. 2021)."""
    from numpyro.diagnostics import effective_sample_size

    flat = x.reshape(x.shape[0], x.shape[1], -1)
    out = np.empty(flat.shape[2])
    for j in range(flat.shape[2]):
        values = flat[:, :, j]
        out[j] = min(
            float(effective_sample_size((values <= q).astype(np.float64)))
            for q in np.percentile(values, ERROR_PERCENTILES)
        )
    return out.reshape(x.shape[2:])


def _converged(stats: dict, tails: dict, ess_target: float) -> bool:
    """Whether every parameter reaches ``ess_target`` effective samples for its mean
    (numpyro's ``summary`` of the chains so far: ``n_eff``, the ESS of the mean) and its error percentiles (``tails``)
    with R-hat at most :data:`R_HAT_STOP`; never for a target of 0 (draw all asked)."""
    if ess_target <= 0:
        return False
    ess = min(float(np.nanmin(np.asarray(s["n_eff"], float))) for s in stats.values())
    tail = min(float(np.nanmin(v)) for v in tails.values())
    r_hat = max(float(np.nanmax(np.asarray(s["r_hat"], float))) for s in stats.values())
    # NaN (a constant parameter) compares False: keep drawing, up to num_samples.
    return bool(min(ess, tail) >= ess_target and r_hat <= R_HAT_STOP)
