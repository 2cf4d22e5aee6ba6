"""Where amigo keeps what it can compute again: latent bases and compiled XLA programs.

``$AMIGO_CACHE_DIR`` names the folder; by default it is ``$XDG_CACHE_HOME/amigo`` or
``~/.cache/amigo``. Nothing in it is needed for correctness: deleting it only costs time.

This module imports neither JAX nor NumPy, so that the command line can point JAX's
persistent compilation cache at the folder before JAX is imported.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: Programs that compile faster than this are not written to the persistent cache. 0: every
#: program is kept. JAX's own default (1 s) left the many small programs of a fit and a
#: detection (one companion's fit, the solver's pieces, eager array operations) to be
#: compiled again in each run: 15 s of a warm `amigo fit`, 8 s of `amigo detect` on a 2-core
#: CPU (docs/performance.md), for a cache that grows by a few MB.
MIN_COMPILE_TIME_S = 0.0


def cache_dir() -> Path:
    """The cache folder (``$AMIGO_CACHE_DIR``, else the XDG cache folder + ``amigo``)."""
    if os.environ.get("AMIGO_CACHE_DIR"):
        return Path(os.environ["AMIGO_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "amigo"


def enable_compilation_cache() -> Path | None:
    """Turn on JAX's persistent compilation cache in ``cache_dir() / "xla-lines"``
    (``"xla"`` where the programs carry full tracebacks: :mod:`amigo.runtime`).

    A second ``amigo fit`` of the same shapes then loads its compiled programs from disk
    instead of compiling them again (minutes on a 2-core CPU). An explicit
    ``JAX_COMPILATION_CACHE_DIR`` wins (an empty value turns the cache off). JAX writes
    the entries under a file lock, so concurrent runs can share the folder.

    The folder depends on what the programs carry in their locations
    (:func:`full_tracebacks`; the command line asks for one line per operation first,
    :func:`amigo.runtime.short_locations`): JAX's cache keys a program without them, so
    a folder filled with full tracebacks (``xla``, JAX's default, and amigo's before
    2026-11-30) would serve those to a process that asked for one line per operation,
    and the other way round. An explicit ``JAX_COMPILATION_CACHE_DIR`` is one folder for
    whatever setting the process has.

    Returns the folder in use, or ``None`` when the cache is off.
    """
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        explicit = os.environ["JAX_COMPILATION_CACHE_DIR"]
        return Path(explicit) if explicit else None
    full = full_tracebacks()
    folder = cache_dir() / ("xla" if full else "xla-lines")
    # Child processes (a manifest's workers, commands started from here) inherit the
    # folder: they must make their programs with the setting that chose it.
    os.environ.setdefault(LOCATIONS_OPTION.upper(), "true" if full else "false")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(folder)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_TIME_S))
    if "jax" in sys.modules:  # amigo used as a library: JAX read its environment already
        import jax

        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update(
            "jax_persistent_cache_min_compile_time_secs",
            float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
        )
    return folder


#: JAX's option (and, upper case, its environment variable) for full Python tracebacks in
#: the programs' locations (:mod:`amigo.runtime`).
LOCATIONS_OPTION = "jax_include_full_tracebacks_in_locations"


def full_tracebacks() -> bool:
    """Whether this process's programs carry full tracebacks in their locations: JAX's
    option where JAX is imported, else its environment variable (JAX's default: yes)."""
    if "jax" in sys.modules:
        import jax

        return bool(getattr(jax.config, LOCATIONS_OPTION))
    value = os.environ.get(LOCATIONS_OPTION.upper(), "true").strip().lower()
    return value in ("1", "true", "t", "yes", "y", "on")
