"""What every reader checks before it opens a path: that it is a regular, readable file.

``open()`` on a FIFO blocks until a writer appears (a hang, not an error), and on a
directory or a socket fails with messages that do not say what is wrong. Every amigo
reader calls :func:`require_file` first, so each of these cases ends in one
:class:`~amigo.errors.InputError` naming the file.
"""

from __future__ import annotations

import contextlib
import hashlib
import numbers
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from astropy.io.fits.verify import VerifyError

from amigo.errors import InputError


def require_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """``path`` as a :class:`Path` if it is a regular file this process may read.

    Raises
    ------
    InputError
        No such file; a directory; a FIFO, socket or device (``what`` says what was
        expected); or not readable (permissions, an unreadable mount).
    """
    path = Path(path)
    try:
        mode = path.stat().st_mode  # follows links: a link to a FIFO is a FIFO
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except OSError as error:
        raise InputError(path, f"cannot be accessed ({error.strerror or error})") from None
    if stat.S_ISDIR(mode):
        raise InputError(path, f"is a directory, not a {what}")
    if not stat.S_ISREG(mode):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a socket or device"
        raise InputError(path, f"is {kind}, not a {what}")
    if not os.access(path, os.R_OK):
        raise InputError(path, "cannot be read (permission denied)")
    return path


#: Bytes read from each end of a file for :func:`fingerprint`.
FINGERPRINT_BYTES = 1 << 20


def fingerprint(path: str | os.PathLike[str]) -> str:
    """A quick identity of a file's content: SHA-256 of its size and its first and last
    MiB (hex, 16 characters). Headers and the last integrations change with any other
    exposure; reading a whole multi-GB ramp file to tell would cost seconds per file."""
    path = Path(path)
    size = path.stat().st_size
    digest = hashlib.sha256(str(size).encode())
    with open(path, "rb") as handle:
        digest.update(handle.read(FINGERPRINT_BYTES))
        if size > FINGERPRINT_BYTES:
            handle.seek(max(FINGERPRINT_BYTES, size - FINGERPRINT_BYTES))
            digest.update(handle.read(FINGERPRINT_BYTES))
    return digest.hexdigest()[:16]


def is_number(value: object) -> bool:
    """A real number as a FITS header or a JSON record holds one (a bool is not one,
    although Python and NumPy count it as an integer)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)


#: What reading a damaged file raises in NumPy and astropy once it has opened: a table
#: column or extension missing or of the wrong type, a value that does not convert, a
#: column format astropy cannot parse (its VerifyError).
DAMAGE = (
    KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError, VerifyError,
)  # fmt: skip


@contextlib.contextmanager
def damaged(path: str | os.PathLike[str], what: str) -> Iterator[None]:
    """Turn the exceptions of :data:`DAMAGE` raised while a reader takes a file apart into
    one :class:`~amigo.errors.InputError` ("malformed ``what`` (...)"); an
    :class:`~amigo.errors.InputError` passes unchanged. Readers wrap only the extraction
    of a file they have opened, so these come from the file, not from amigo."""
    try:
        yield
    except InputError:
        raise
    except DAMAGE as error:
        raise InputError(path, f"malformed {what} ({type(error).__name__}: {error})") from None
