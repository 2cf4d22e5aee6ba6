"""Write outputs atomically: to a temporary name in the same folder, then rename.

A crash or Ctrl-C half-way through never leaves a truncated product under its final name,
and an existing file is replaced in one step.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from amigo.errors import InputError

#: Errors of the output folder, not of amigo: a full disk or quota, a read-only file
#: system, no permission, an output path that is a file (or under one).
#: :func:`atomic_path` reports them as the user's problem.
OUTPUT_ERRNOS = frozenset(
    {
        errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
        errno.ENOTDIR, errno.EEXIST, errno.EISDIR,
    }
)  # fmt: skip


def unwritable(path: str | os.PathLike[str] | None, error: OSError) -> InputError:
    """The one line for an output that cannot be written (``error.errno`` in
    :data:`OUTPUT_ERRNOS`), naming ``path``."""
    if error.errno in (errno.EEXIST, errno.ENOTDIR) and path is not None and Path(path).is_file():
        # mkdir of an output folder that is a file (errno EEXIST, "File exists"): said
        # plainly. (A folder under a file, ENOTDIR, names the folder: "Not a directory".)
        return InputError(path, "is a file, where amigo needs a folder for its outputs")
    reason = os.strerror(error.errno) if error.errno is not None else str(error)
    return InputError(path, f"cannot be written ({reason})")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temporary file keeps the final suffix (``.fits``, ``.json``...) so that writers
    which infer the format from the name behave. Whatever happens, no temporary file is
    left; a full disk, a read-only folder or a missing permission (:data:`OUTPUT_ERRNOS`)
    becomes one :class:`~amigo.errors.InputError` naming ``path``, and ``path`` keeps its
    previous content, if any.
    """
    final = Path(path)
    tmp: Path | None = None
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{final.stem}.", suffix="".join(final.suffixes) or ".tmp", dir=final.parent
        )
        os.close(fd)
        tmp = Path(tmp_name)
        tmp.unlink()  # let writers that refuse to overwrite create it themselves
        yield tmp
        os.replace(tmp, final)
    except OSError as error:
        if error.errno in OUTPUT_ERRNOS:
            raise unwritable(final, error) from None
        raise
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()


def write_text(path: str | os.PathLike[str], text: str) -> None:
    """Atomically write a text file (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
