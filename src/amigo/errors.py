"""Exception types shared by the whole package.

Every problem with a user's input is raised as :class:`InputError`, which names the file
and says what is wrong in one line. The command line turns it into that one line on
stderr and exit status 2; anything else is an internal error (exit status 1).
"""

from __future__ import annotations

import os


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
