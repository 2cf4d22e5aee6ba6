"""Levenberg-Marquardt (damped Gauss-Newton) with chord steps, for any least-squares problem.

The solver sees a parameter vector and a :class:`Problem`: the loss ``L = chi2 / 2``, its
gradient ``g`` (``-dL/dx``, the direction of descent) and the normal equations ``(F, g)``
with the Fisher (Gauss-Newton) matrix ``F = J^T W J``. It knows nothing of images or
instruments (:mod:`amigo.fitting.newton` builds the fit's problem).

A step solves ``(F_s + mu I) d_s = g_s`` in Jacobi-scaled coordinates (``F_s = D^-1 F D^-1``,
``D = sqrt(diag F)``). Exact degeneracies are dropped by an eigenvalue floor
(:data:`EIGEN_FLOOR`); ``mu`` grows when a step does not lower the loss and shrinks when it
does. The natural gradient with the *full* Fisher matrix, taken with a unit step, is
exactly this Gauss-Newton step.

Convergence is the Newton decrement ``g^T F^+ g`` (twice the decrease of ``L`` that a full
step would give) per group (an exposure, in the fits), below the settings' tolerance times
``max(1, 2 L / n_values)``.

Chord steps
-----------
Where a Fisher matrix costs much more than a gradient (the fits: seconds against a
fraction of a second), the solver keeps the last Fisher matrix and takes up to
``settings.chord_steps`` steps with fresh gradients only (the frozen-Jacobian, or chord,
Gauss-Newton method; it converges linearly at the rate at which ``F`` changes). When a
chord step's decrement estimate falls below the tolerance, the next normal equations are
asked for in float64 (``problem.float64 = True``): if they confirm convergence, one last
undamped step is taken with that exact matrix (a loss evaluation: it brings the vector
quadratically close to the optimum, which the tolerance alone leaves up to ~1 sigma away
along one direction), and the matrix is returned with the solution.

Noise model
-----------
What the likelihood takes from the residuals (the 1/f stripes of a level-2 image,
:meth:`Problem.refresh`) is measured where new Jacobians are taken, so that each Fisher
matrix is the likelihood's at its point, but not at a cold start: there the model's own
errors fill the image's halo, where the stripes are measured, and the estimate is
spurious (on a simulated pair without stripes, stripes "found" at the start and dropped
at the next Jacobians raised chi2 by ~1000 and cost the fit a set of Jacobians). The
first measurement is taken at the second set of Jacobians, or, where the first set's
chord steps already converge, before the confirmation (in float64, as the confirmation):
if it changes the likelihood, new Jacobians are taken for it. A fit that stops before
either (its iterations spent, or no step lowering the loss) measures it before it
returns, unconverged or with its matrix dropped where that changed the likelihood, so
that what follows (the latent Hessians, the next stage) has it. A given matrix comes from
a solution of the same exposures, whose noise model was measured before it returned.

Confirmation
------------
What the confirmation needs in float64 is the gradient: float32 rounding of the model
puts a floor of about one chi2 unit per group on the decrement. The Fisher matrix only
weighs it, and ``F`` changes little over the distances the tolerance speaks of (the
Jacobians' relative change over a displacement is the displacement over the scale on
which the model is non-linear; on the real F480M pair of docs/performance.md, taking
the matrix up to ~2 sigma from the optimum instead of ~1 moved the DISCOs' information
matrix by 1.4e-3 and their errors by at most 1.2e-3 of themselves). So where the vector
is still within :data:`STALE_FISHER_REACH` of the point of the last Jacobians, the
float64 gradient there is weighed by that matrix, and new Jacobians are evaluated only if
it does not confirm convergence. The returned matrix is then the one of those Jacobians,
and that distance is the one the caller's covariances are taken across.

The reach is a distance *per parameter*: ``dx^T F dx`` over the number of parameters the
matrix informs, in tolerances, at most 1, i.e. a root-mean-square move of about one
sigma per parameter at the default tolerance. It replaced 4 tolerances per group
(2026-11-28), which sent the real fits' refits after a detector correction to new
Jacobians only to confirm (they move by a decrement of 30-900 per exposure of ~1100
parameters; 6 of a three-filter fit's 20 sets, docs/performance.md, the eleventh
session). The price is in the covariances' last digits: where a parameter to which the
matrix is sensitive moved far on the way (the jitter: the blur's transfer at the longest
baselines changes by ~1 % per sigma of a real fit's jitter), the matrix differs from the
optimum's by up to ~1 % on its diagonal and the errors by up to ~0.5 % (0.01 % within
the old reach), below the ~2 % to which the data calibrate the errors afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from amigo.progress import step

#: A chord step whose fall of ``L`` is below this fraction of the fall the stale Fisher
#: matrix predicts (half the decrement estimate) calls for new Jacobians. Low on purpose:
#: far from the noise the Gauss-Newton model itself over-predicts every step (fresh
#: Jacobians predict no better), and a chord step costs ~1/50 of a Jacobian.
CHORD_EFFICIENCY = 0.05
#: Eigenvalues of the Jacobi-scaled Fisher matrix below this fraction of the largest are
#: treated as exact degeneracies: the Jacobians are float32 (~1e-7 relative noise), so
#: smaller eigenvalues are set by rounding, and the gradient's rounding noise along them
#: would dominate both the step and the Newton decrement.
EIGEN_FLOOR = 1e-7
#: How far (``dx^T F dx`` per parameter the matrix informs, in units of the tolerance)
#: the vector may have moved from where the last Jacobians were evaluated for that Fisher
#: matrix to confirm convergence with a float64 gradient alone (module notes,
#: "Confirmation"): 1, a root-mean-square move of about one sigma per parameter at the
#: default tolerance.
STALE_FISHER_REACH = 1.0


class Problem(Protocol):
    """A least-squares problem as :func:`minimise` sees it (float64 NumPy vectors)."""

    #: Values in the likelihood (pixels), for the tolerance's ``chi2 / n`` scaling.
    n_values: float
    #: Independent groups (exposures) the decrement is normalised by.
    n_groups: int
    #: Whether the model runs in float64; the solver switches it on near the optimum.
    float64: bool

    def loss(self, vector: np.ndarray) -> float:
        """``L = chi2 / 2`` (priors included) at ``vector``."""
        ...

    def gradient(self, vector: np.ndarray) -> np.ndarray:
        """``-dL/dx`` at ``vector``."""
        ...

    def normal_equations(self, vector: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
        """The Fisher matrix ``F`` and the gradient ``g`` at ``vector``."""
        ...

    def refresh(self, vector: np.ndarray) -> bool:
        """Re-measure, at ``vector``, what the noise model takes from the residuals (e.g.
        1/f stripes); ``True`` when that changed the loss. Called before new Jacobians
        (not the cold start's first), before the first confirmation where none was taken
        since, and at the end if never before (module notes, "Noise model")."""
        ...


class Settings(Protocol):
    """What :func:`minimise` reads of its settings (e.g. :class:`amigo.fitting.newton.NewtonConfig`)."""

    # Read-only (properties), so that a frozen dataclass satisfies the protocol.
    @property
    def max_iterations(self) -> int: ...
    @property
    def tolerance(self) -> float: ...
    @property
    def damping(self) -> float: ...
    @property
    def chord_steps(self) -> int: ...
    @property
    def float64_check(self) -> bool: ...


def _pseudo_inverse_diagonal(
    rows: np.ndarray, evals: np.ndarray, keep: np.ndarray, root: np.ndarray
) -> np.ndarray:
    """``(F^+)_ii`` from the eigenpairs of the Jacobi-scaled ``F_s = D^-1 F D^-1``:
    ``rows`` (n, m) the eigenvectors' entries of the parameters asked for, ``evals`` (m,)
    the eigenvalues, ``keep`` (m,) those above the floor, ``root`` (n,) their ``D``; NaN
    where no kept direction informs a parameter."""
    inverse = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    variance = (rows**2 @ inverse) / root**2
    return np.where(variance > 0, variance, np.nan)


def _jacobi_scaled(fisher: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(active, D, F_s)``: the parameters with information (``diag F > 0``), their
    ``D = sqrt(diag F)``, and ``F_s = D^-1 F D^-1`` on them."""
    diag = np.diag(fisher)
    active = np.nonzero(diag > 0)[0]
    root = np.sqrt(diag[active])
    return active, root, fisher[np.ix_(active, active)] / np.outer(root, root)


class FisherSolve:
    """``(F_s + mu I)^-1 g_s`` for one Fisher matrix and any gradient and damping.

    In Jacobi-scaled coordinates (``F_s = D^-1 F D^-1``, ``D = sqrt(diag F)``), on the
    parameters with information (``diag F > 0``; the others get no step), with exact
    degeneracies (eigenvalues below :data:`EIGEN_FLOOR` of the largest) dropped. The
    eigendecomposition is done once: a Levenberg-Marquardt iteration solves with the same
    matrix for several dampings and, in chord steps, several gradients.
    """

    def __init__(self, fisher: np.ndarray) -> None:
        self.size = fisher.shape[0]
        self.active, self.root, scaled = _jacobi_scaled(fisher)
        evals, self.evecs = np.linalg.eigh(scaled)
        self.keep = evals > EIGEN_FLOOR * evals.max() if evals.size else evals > 0
        self.evals = np.where(self.keep, evals, 1.0)

    def __call__(self, grad: np.ndarray, damping: float = 0.0) -> np.ndarray:
        inv = np.where(self.keep, 1.0 / (self.evals + damping), 0.0)
        scaled = self.evecs @ (inv * (self.evecs.T @ (grad[self.active] / self.root)))
        step = np.zeros(self.size)
        step[self.active] = scaled / self.root
        return step

    def variances(self, indices: np.ndarray) -> np.ndarray:
        """``(F^+)_ii`` of the matrix's entries ``indices`` (all others marginalised), from
        the decomposition already made; NaN where an entry has no information here."""
        indices = np.asarray(indices, int)
        out = np.full(indices.shape, np.nan)
        if self.active.size == 0:
            return out
        position = np.minimum(np.searchsorted(self.active, indices), self.active.size - 1)
        inside = self.active[position] == indices
        at = position[inside]
        out[inside] = _pseudo_inverse_diagonal(self.evecs[at], self.evals, self.keep, self.root[at])
        return out


def marginal_errors(
    fisher: np.ndarray | None, indices: np.ndarray, solves: tuple[FisherSolve, ...] = ()
) -> np.ndarray:
    """Standard errors ``sqrt((F^+)_ii)`` of the global vector's entries ``indices``
    (all others marginalised), from a fit's Fisher matrix (priors included); exact
    degeneracies are dropped as in the solver (:class:`FisherSolve`). NaN where ``fisher``
    is ``None`` or the parameter has no information.

    ``solves``: the solver's own decompositions of the parts of ``fisher`` that never
    meet (:attr:`Solution.solve` of each stage whose matrix ``fisher`` sums), read
    instead of decomposing again; each has its own eigenvalue floor, that of its
    stage's largest eigenvalue (the same errors to the decompositions' rounding where no
    eigenvalue lies between the two floors; tests/test_newton.py).

    The matrix of a filter's fit sums its groups' matrices, which never meet (the science
    exposures' parameters are not the calibrators'): its blocks are decomposed apart, the
    whole matrix's eigenpairs for a quarter of the work (two blocks of ~1100 for a real
    pair of exposures: 1.0 -> 0.25 s on 2 cores, docs/performance.md)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    indices = np.asarray(indices, int)
    out = np.full(indices.shape, np.nan)
    if fisher is None:
        return out
    if solves:
        diagonal = np.diag(fisher)
        for solve in solves:
            # A decomposition of another matrix would give other errors without a sign.
            if solve.size != fisher.shape[0] or not np.allclose(
                solve.root**2, diagonal[solve.active], rtol=1e-9, atol=0.0
            ):
                raise ValueError("a decomposition of another Fisher matrix")
        for solve in solves:
            variance = solve.variances(indices)
            found = np.isfinite(variance)
            out[found] = np.sqrt(variance[found])
        return out
    active, root, scaled = _jacobi_scaled(fisher)
    if active.size == 0:
        return out
    _, labels = connected_components(csr_matrix(scaled != 0), directed=False)
    blocks = [np.nonzero(labels == b)[0] for b in range(labels.max() + 1)]
    pairs = [np.linalg.eigh(scaled[np.ix_(block, block)]) for block in blocks]
    # The floor is the whole matrix's: relative to its largest eigenvalue, any block's.
    floor = EIGEN_FLOOR * max(float(evals.max()) for evals, _ in pairs)
    position = {int(a): k for k, a in enumerate(active)}
    for k, i in enumerate(indices):
        p = position.get(int(i))
        if p is None:
            continue
        evals, evecs = pairs[labels[p]]
        row = evecs[np.searchsorted(blocks[labels[p]], p)]
        out[k] = np.sqrt(_pseudo_inverse_diagonal(row, evals, evals > floor, root[p]))
    return out


@dataclass
class Solution:
    """Outcome of :func:`minimise`: the final vector, and ``fisher`` when float64
    residuals confirmed convergence, else ``None``: the matrix of the last Jacobians,
    evaluated within :data:`STALE_FISHER_REACH` (per parameter) of the point of confirmation,
    from which the final vector is one undamped Gauss-Newton step (module notes,
    "Confirmation")."""

    vector: np.ndarray
    converged: bool
    iterations: int
    chord_steps: int
    decrement: float
    history: list[float]
    fisher: np.ndarray | None
    #: Fall of the loss over the last iteration (where its normal equations confirmed
    #: convergence, that of the final undamped step alone: ~0).
    last_fall: float = 0.0
    #: The last Fisher matrix used (float32 or float64; at or near the final vector).
    last_fisher: np.ndarray | None = None
    #: The solver's decomposition of ``fisher`` (with ``fisher``, else ``None``), which
    #: :func:`marginal_errors` reads rather than decomposing the matrix again.
    solve: FisherSolve | None = None


def minimise(
    problem: Problem,
    vector: np.ndarray,
    config: Settings,
    label: str,
    fisher: np.ndarray | None = None,
    exact: bool = True,
) -> Solution:
    """Levenberg-Marquardt with chord steps from ``vector`` (see module notes).

    ``fisher``: a Fisher matrix of this problem's model that the caller has (a refit of
    the same model to corrected data: ``F = J^T W J`` does not depend on the data). The
    first iteration takes it instead of new Jacobians. ``exact``: it is the float64 matrix
    *at* ``vector``; then the first gradient is float64 too, and convergence may be
    declared at once. Otherwise (float32 Jacobians, or another point) it only steers the
    first chord steps, and new Jacobians confirm.
    """
    n_groups = float(problem.n_groups)
    loss = problem.loss(vector)
    history = [loss]
    damping = config.damping
    decrement = np.inf
    estimate = np.inf  # decrement predicted with the last Fisher matrix
    converged = False
    iteration = chords = 0
    given, given_exact = fisher is not None, exact
    exact = False  # whether the last decrement came from float64 residuals at `vector`
    # Where the Jacobians of `fisher` were evaluated (None: not known, e.g. a matrix
    # given from another fit), and whether it has already been tried as a confirmation.
    fisher_point = np.array(vector, copy=True) if given and given_exact else None
    stale_tried = False
    solver: FisherSolve | None = None  # the decomposition of `fisher`
    # Whether the noise model has been measured on this problem's residuals (module
    # notes, "Noise model"); a given matrix comes with the noise model of its fit.
    measured = given
    measured_at: np.ndarray | None = None  # where it was last measured

    def tolerance() -> float:
        return config.tolerance * max(1.0, 2.0 * loss / problem.n_values)

    def near(matrix: np.ndarray | None, point: np.ndarray | None) -> bool:
        """Whether ``vector`` is within :data:`STALE_FISHER_REACH` of ``point``, where
        the Jacobians of ``matrix`` were evaluated (``dx^T F dx`` per parameter with
        information: a stage of a fit sees its own block of a larger matrix)."""
        if matrix is None or point is None or not config.float64_check:
            return False
        dx = vector - point
        informed = max(int(np.count_nonzero(np.diag(matrix) > 0)), 1)
        return float(dx @ matrix @ dx) / informed <= STALE_FISHER_REACH * tolerance()

    def damped_step(solver, grad) -> float | None:
        """A Levenberg-Marquardt step from ``vector``: the fall of the loss, or None if
        no damping makes the loss fall (the damping is then left as it was: the next
        matrix starts from it, not from the search's 4^12 times more)."""
        nonlocal vector, loss, damping
        entry = damping
        for _ in range(12):
            trial = vector + solver(grad, damping)
            trial_loss = problem.loss(trial)
            if np.isfinite(trial_loss) and trial_loss < loss:
                fall = loss - trial_loss
                vector, loss = trial, trial_loss
                damping = max(damping / 3.0, 1e-9)
                history.append(loss)
                return fall
            damping *= 4.0
        damping = entry
        return None

    def final_step(solver, grad) -> None:
        """The undamped Gauss-Newton step with the exact matrix that confirmed convergence.

        The tolerance lets the vector stop up to ~1 sigma from the optimum along one
        direction (a decrement of 1), so where it stops depends on the path: on a GPU
        and on a CPU the same fit landed 0.55 sigma apart in one jitter. One more step
        with the float64 matrix, at the cost of one loss, lands quadratically close to
        the optimum (the matrix barely changes over a sigma), so the result no longer
        depends on the machine that found it."""
        nonlocal vector, loss
        trial = vector + solver(grad, 0.0)
        trial_loss = problem.loss(trial)
        if np.isfinite(trial_loss) and trial_loss <= loss:
            vector, loss = trial, trial_loss
            history.append(loss)

    def measure() -> bool:
        """Measure the noise model at ``vector`` (:meth:`Problem.refresh`); ``True`` when
        that changed the loss (then re-evaluated)."""
        nonlocal loss, measured, measured_at
        measured, measured_at = True, np.array(vector, copy=True)
        if not problem.refresh(vector):
            return False
        loss = problem.loss(vector)
        history.append(loss)
        return True

    def to_float64() -> None:
        """From here on the model runs in float64 (the loss is re-evaluated in it)."""
        nonlocal loss
        if config.float64_check and not problem.float64:
            problem.float64 = True
            loss = problem.loss(vector)
            history.append(loss)

    start_loss = loss
    for iteration in range(1, config.max_iterations + 1):
        confirm = estimate < tolerance() and not stale_tried and near(fisher, fisher_point)
        if confirm and not measured:
            to_float64()  # measured on the residuals the confirmation would take
            if measure():
                confirm = False  # the last matrix is of another likelihood now
        if given and iteration == 1:
            assert fisher is not None  # given
            if given_exact:  # exact at `vector`: only the gradient is new (in float64)
                to_float64()
            grad = problem.gradient(vector)
            exact = problem.float64 and given_exact
            solver = FisherSolve(fisher)
            source = "the given Fisher matrix"
        elif confirm:
            # Confirmation by a float64 gradient, weighed by the last Fisher matrix and
            # its decomposition (module notes, "Confirmation").
            to_float64()
            grad = problem.gradient(vector)
            exact = problem.float64
            stale_tried = True
            source = "float64 residuals, the last Fisher matrix"
        else:
            if estimate < tolerance():
                to_float64()  # these Jacobians are expected to confirm convergence
            # The old matrix and its decomposition are replaced: let them go before the
            # new Jacobians are taken (the fits' matrices are tens of MB each).
            fisher = solver = None
            # Not at a cold start (module notes, "Noise model"), nor again where it was
            # just measured (before a confirmation that it then called off).
            if iteration > 1 and not (measured_at is not None and np.array_equal(vector, measured_at)):  # fmt: skip
                measure()
            fisher, grad = problem.normal_equations(vector, label)
            fisher_point, stale_tried = np.array(vector, copy=True), False
            solver = FisherSolve(fisher)
            exact = problem.float64
            source = "new Jacobians"
        start_loss = loss  # after any switch to float64: a fall, not a rounding change
        assert solver is not None  # every branch above has one
        decrement = float(grad @ solver(grad)) / n_groups
        step(
            f"{label}: Gauss-Newton {iteration}: chi2 {2 * loss:.2f}, "
            f"Newton decrement {decrement:.3g} per exposure ({source})"
        )
        if decrement < tolerance():
            approximate = given and iteration == 1 and not given_exact
            if not approximate and (exact or not config.float64_check):
                if not measured and measure():
                    estimate = np.inf  # another likelihood: new Jacobians
                    continue
                converged = True
                if exact:
                    final_step(solver, grad)
                break
            # An approximate matrix's decrement is an estimate: new Jacobians confirm. A
            # float32 one is confirmed by the float64 gradient at this point, weighed by
            # the same matrix (the next iteration; module notes, "Confirmation").
            estimate = decrement
            continue
        if damped_step(solver, grad) is None:
            if problem.float64 or not config.float64_check:
                step(f"{label}: no damped step lowers the loss; stopping")
                break
            # float32 may not resolve the remaining fall of the loss: go on in float64.
            to_float64()
            step(f"{label}: continuing in float64")
            estimate = np.inf
            continue
        exact = False
        estimate = np.inf
        for _ in range(config.chord_steps):
            grad = problem.gradient(vector)
            estimate = float(grad @ solver(grad)) / n_groups
            if estimate < tolerance():
                break  # new Jacobians (float64) to confirm
            fall = damped_step(solver, grad)
            if fall is None:
                break
            chords += 1
            if fall < CHORD_EFFICIENCY * 0.5 * estimate * n_groups:
                break  # the stale Fisher matrix no longer predicts the fall: new Jacobians
        step(
            f"{label}: {chords} chord steps so far, chi2 {2 * loss:.2f}, "
            f"decrement estimate {estimate:.3g} per exposure"
        )
    if not measured and measure():
        # Stopped before any measurement (iterations spent, or no step lowering the
        # loss): measured now for what follows; a matrix of the old likelihood is not
        # the solution's.
        converged, exact = False, False
    return Solution(
        vector=vector,
        converged=converged,
        iterations=iteration,
        chord_steps=chords,
        decrement=decrement,
        history=history,
        fisher=fisher if (converged and exact) else None,
        last_fall=start_loss - loss,
        last_fisher=fisher,
        solve=solver if (converged and exact) else None,
    )
