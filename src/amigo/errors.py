"""Exception types shared by the whole package.

Every problem with a user's input is raised as :class:`InputError`, which names the file
and says what is wrong in one line. The command line turns it into that one line on
stderr and exit status 2; anything else is an internal error (exit status 1).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import numpy as np


class AmigoError(Exception):
    """Base class of all errors raised on purpose by amigo."""


class InputError(AmigoError):
    """A user-supplied file or option is unusable.

    Parameters
    ----------
    path
        The offending file (or ``None`` for a problem not tied to one file).
    problem
        What is wrong, as a short phrase an astronomer understands
        (``"PUPIL is 'CLEARP', expected 'NRM'"``).
    """

    def __init__(self, path: str | os.PathLike[str] | None, problem: str) -> None:
        self.path = None if path is None else os.fspath(path)
        # One line, whatever a library's message quoted: the contract is one line per file.
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.path}: {self.problem}" if self.path else self.problem)


class ReportedInputError(InputError):
    """Bad inputs whose lines are on stderr already (one per file, from a batch that went
    on with the other files): the command line exits with status 2 and adds no line."""


class TooFewPixels(InputError):
    """An image with fewer usable pixels than a fit needs (every pixel flagged, say): a
    problem of one exposure, which ``amigo fit`` leaves out of a filter that has others."""


class NumericalFailure(AmigoError):
    """A computation on valid input that has no usable result: a singular matrix, values
    that are not finite, a covariance that is not positive definite.

    ``amigo fit`` reports it per filter (``fit_summary.json``, status ``"failed"``) and goes
    on with the other filters, instead of ending in a traceback.

    Parameters
    ----------
    stage
        Which step failed (``"latent covariance"``).
    problem
        What went wrong, one line.
    """

    def __init__(self, stage: str, problem: str) -> None:
        self.stage = stage
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{stage}: {self.problem}")


#: What NumPy and SciPy raise for a matrix or value without a result.
NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError)


@contextlib.contextmanager
def numerical(stage: str) -> Iterator[None]:
    """Turn a linear-algebra or floating-point error of the block into a
    :class:`NumericalFailure` of ``stage``."""
    try:
        yield
    except NUMERICAL_ERRORS as error:
        raise NumericalFailure(stage, f"{type(error).__name__}: {error}") from error


def require_finite(stage: str, what: str, *arrays: object) -> None:
    """Raise :class:`NumericalFailure` of ``stage`` unless every value of ``arrays`` is
    finite (``what``: the values' name for the message)."""
    for array in arrays:
        values = np.asarray(array, dtype=float)
        if not np.all(np.isfinite(values)):
            bad = int(np.sum(~np.isfinite(values)))
            raise NumericalFailure(stage, f"{bad} of {values.size} {what} are not finite")
