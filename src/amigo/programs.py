"""Traced programs kept on disk: a second run skips JAX's tracing and lowering too.

JAX's persistent compilation cache (:func:`amigo.cachedir.enable_compilation_cache`) keeps
XLA's *compiled* programs, but a new process still traces every Python function into a
jaxpr and lowers it to StableHLO before it can even look the program up: on a 2-core CPU,
29 of the 36 s that a warm three-filter ``amigo fit`` spent compiling (docs/performance.md).
:func:`jit` is :func:`equinox.filter_jit` that also keeps the lowered program, serialized
by :mod:`jax.export`, in ``cache_dir() / "programs" / <source version>``; the next process
with the same key deserializes it (milliseconds) and hands it to XLA, whose own cache then
has it compiled.

The key is exact, never approximate: a program is reused only where tracing again would
give the same program. It holds

* the package's source (a hash of every ``.py`` file of amigo: an edit is a new program),
  the versions of the libraries traced into the programs (JAX, jaxlib, NumPy, equinox,
  numpyro, optax, optimistix), the backend, the precision and promotion options, and
  the environment variables read while tracing (:data:`TRACED_VARIABLES`:
  ``AMIGO_JVP_BATCH``) at the value in effect;
* the function's module, qualified name and file (a function outside amigo is keyed on
  its own source);
* the arguments' structure, with every static value in full (the fields of a module marked
  static, the non-array leaves: numbers, strings, tuples, NumPy arrays by their bytes) and
  every array by its shape, dtype and weak type only (what tracing sees).

An argument that cannot be fingerprinted exactly (a closure, an object of unknown kind) or
a program that :mod:`jax.export` refuses (a host callback) falls back to plain
:func:`equinox.filter_jit`, as does a call made while tracing (the function is inlined
into its caller's program). So does every call when the compilation cache is off: the
programs live beside the compiled ones and are switched on and off with them.

:func:`side_by_side` runs independent calls of compiled programs in threads: XLA runs
amigo's matrix products on one thread each (:mod:`amigo.runtime`), so one program alone
leaves part of a CPU idle.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import importlib
import inspect
import json
import logging
import os
import sys
import tempfile
import threading
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from amigo import heap
from amigo.cachedir import LOCATIONS_OPTION, cache_dir

#: Bumped when the file format or the key's recipe changes.
FORMAT = 1

_log = logging.getLogger("amigo.programs")


class _Uncacheable(Exception):
    """An argument whose value cannot be fingerprinted exactly."""


# ---------------------------------------------------------------------------- the key
def _named(obj: Any) -> str | None:
    """``module:qualname`` when that name imports back to ``obj`` itself (module-level
    functions and classes, JAX's functions), else ``None``."""
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if not isinstance(module, str) or not isinstance(qualname, str) or "<" in qualname:
        return None
    target: Any = sys.modules.get(module)
    for part in qualname.split("."):
        target = getattr(target, part, None)
    return f"{module}:{qualname}" if target is obj else None


def _static(obj: Any, out: list[str]) -> None:
    """Append an exact fingerprint of a static value to ``out`` (raise
    :class:`_Uncacheable` where none is known)."""
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        out.append(f"{type(obj).__name__}:{obj!r}")  # repr of a float is exact
    elif isinstance(obj, np.generic):
        out.append(f"np.{obj.dtype.str}:{obj.item()!r}")
    elif isinstance(obj, np.ndarray):
        digest = hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest()
        out.append(f"ndarray:{obj.dtype.str}:{obj.shape}:{digest}")
    elif isinstance(obj, jax.Array):
        raise _Uncacheable("a JAX array in a static position")
    elif isinstance(obj, (tuple, list, frozenset, set)):
        items = sorted(obj, key=repr) if isinstance(obj, (set, frozenset)) else obj
        kind = type(obj)  # a named tuple's type counts
        out.append(f"{kind.__module__}.{kind.__qualname__}[{len(items)}]")
        for item in items:
            _static(item, out)
    elif isinstance(obj, dict):
        out.append(f"dict[{len(obj)}]")
        for key in sorted(obj, key=repr):
            _static(key, out)
            _static(obj[key], out)
    elif isinstance(obj, enum.Enum):
        out.append(f"enum:{_named(type(obj))}:{obj.name}")
    elif isinstance(obj, functools.partial):
        out.append("partial")
        _static((obj.func, obj.args, obj.keywords), out)
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        name = _named(type(obj))
        if name is None:
            raise _Uncacheable(f"a dataclass of a local class {type(obj).__qualname__}")
        fields = dataclasses.fields(obj)
        out.append(f"dataclass:{name}[{len(fields)}]")
        for field in fields:
            out.append(field.name)
            _static(getattr(obj, field.name), out)
    elif (name := _named(obj)) is not None:
        out.append(f"named:{name}")  # a module-level function or class
    elif _stateless(obj):
        out.append(f"stateless:{_named(type(obj))}")  # a sentinel, e.g. equinox's Missing
    else:
        raise _Uncacheable(f"no exact fingerprint of a {type(obj).__qualname__}")


def _stateless(obj: Any) -> bool:
    """Whether ``obj`` is an instance of a module-level Python class that holds no state:
    an empty instance dictionary and no slots (an object of a compiled type, whose state
    Python cannot see, never is)."""
    if _named(type(obj)) is None or isinstance(obj, types.FunctionType):
        return False
    if not hasattr(obj, "__dict__") or obj.__dict__:
        return False
    return not getattr(type(obj), "__slots__", ())


def _structure(treedef: Any, out: list[str]) -> None:
    """Fingerprint a pytree's structure, static data of every node included."""
    node = treedef.node_data()
    if node is None:
        out.append("*")
        return
    kind, aux = node
    name = "NoneType" if kind is type(None) else _named(kind)
    if name is None:
        raise _Uncacheable(f"a pytree node of a local class {kind.__qualname__}")
    out.append(f"node:{name}")
    _static(aux, out)
    children = treedef.children()
    out.append(f"children[{len(children)}]")
    for child in children:
        _structure(child, out)


#: Digests of the structures met in this process. A structure equal to a known one (by
#: the equality of its static data, as JAX's own jit caches compare them) has its digest:
#: the fingerprint of a dataset's structure walks ~10^5 static values (3 ms).
_DIGESTS: dict[Any, str] = {}


def _structure_digest(treedef: Any) -> str:
    """:func:`_structure`'s fingerprint of ``treedef``, hashed, remembered per structure."""
    try:
        return _DIGESTS[treedef]
    except KeyError:
        pass
    except TypeError:  # unhashable static data: fingerprinted every time
        return _digest_of(treedef)
    digest = _DIGESTS[treedef] = _digest_of(treedef)
    return digest


def _digest_of(treedef: Any) -> str:
    parts: list[str] = []
    _structure(treedef, parts)
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _encode(treedef: Any) -> Any:
    """An output structure as JSON: plain containers and module-level named tuples only
    (their types are found again by name), leaves as ``"*"``."""
    node = treedef.node_data()
    if node is None:
        return "*"
    kind, aux = node
    children = [_encode(child) for child in treedef.children()]
    if kind in (tuple, list):
        return {"type": kind.__name__, "children": children}
    if kind is type(None):
        return {"type": "None"}
    if kind is dict and all(isinstance(k, str) for k in aux):
        return {"type": "dict", "keys": list(aux), "children": children}
    if issubclass(kind, tuple) and hasattr(kind, "_fields") and (name := _named(kind)):
        return {"type": "namedtuple", "name": name, "children": children}
    raise _Uncacheable(f"an output of a kind not kept: {kind.__qualname__}")


def _decode(code: Any) -> Any:
    """The structure :func:`_encode` wrote, as a pytree whose leaves are ``0``."""
    if code == "*":
        return 0
    kind = code["type"]
    children = [_decode(c) for c in code.get("children", ())]
    if kind == "None":
        return None
    if kind == "dict":
        return dict(zip(code["keys"], children, strict=True))
    if kind == "namedtuple":
        module, qualname = code["name"].split(":")
        target: Any = importlib.import_module(module)
        for part in qualname.split("."):
            target = getattr(target, part)
        return target(*children)
    return tuple(children) if kind == "tuple" else children


def _aval(leaf: Any) -> tuple[tuple[int, ...], np.dtype, bool]:
    """(shape, dtype, weak type) of an array leaf: all that tracing sees of it."""
    # NumPy's float64 is traced as float32 unless x64 is on: the canonical dtype.
    dtype = np.dtype(jax.dtypes.canonicalize_dtype(leaf.dtype))
    return tuple(np.shape(leaf)), dtype, bool(getattr(leaf, "weak_type", False))


@functools.cache
def _source_digest() -> str:
    """Hash of amigo's Python source: any edit makes every program new."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


@functools.cache
def _file_digest(path: str) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return "unreadable"


def _config(name: str) -> Any:
    """A JAX option's value in this thread (``jax.enable_x64`` and the like included)."""
    return getattr(jax.config, name)


def _device_platform() -> str:
    """The platform this thread's programs run on: the default device's where one is set
    (``jax.default_device``: NUTS's chains on the host, :func:`latency_device`), else
    the default backend's."""
    device = _config("jax_default_device")
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def latency_device() -> Any | None:
    """The CPU device, where ``AMIGO_SAMPLER_DEVICE=host`` sends latency-bound programs
    instead of the default accelerator; ``None`` where they run where JAX runs everything
    (the default backend is the CPU, the setting is ``default``, or JAX has no CPU backend
    in this process).

    A chain of NUTS is thousands of small steps one after the other, each a handful of
    matrix-vector products of ~1000 rows: on an accelerator each step waits on kernel
    launches and on the while loops' conditions read back by the host. Measured on an
    H200's machine, the host saved 1.8 of NUTS's 14.7 s and was slower on the joint
    posterior (docs/performance.md, "On a GPU, a sixth time"): not the default.
    """
    from amigo.runtime import sampler_device_setting

    if sampler_device_setting() == "default" or jax.default_backend() == "cpu":
        return None
    try:
        return jax.devices("cpu")[0]
    except RuntimeError:  # JAX_PLATFORMS without the CPU
        return None


def on_device(tree: Any, device: Any | None) -> Any:
    """``tree`` with its arrays committed to ``device`` (unchanged for ``None``); the other
    leaves (static numbers, strings) stay as they are, so programs keep their keys."""
    if device is None:
        return tree
    return jax.tree.map(lambda x: jax.device_put(x, device) if eqx.is_array(x) else x, tree)


#: Libraries whose code is traced into amigo's programs (numpyro's NUTS, equinox's
#: modules, NumPy's constants): a new version is a new program.
TRACED_LIBRARIES = ("jax", "jaxlib", "numpy", "equinox", "numpyro", "optax", "optimistix")


@functools.cache
def _versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    def one(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "none"

    return ",".join(f"{name}={one(name)}" for name in TRACED_LIBRARIES)


#: Environment variables that a traced program reads, each with the value a trace takes
#: where it is unset (the Jacobians' batch of columns, :func:`amigo.model.columns.jvp_batch`,
#: default :data:`~amigo.model.columns.JVP_BATCH`; tests/test_programs.py checks that they
#: agree): part of every key as the value in effect, so that unset and set to the
#: default are one program. No other variable changes a program, and setting one
#: (``AMIGO_DEBUG`` for a traceback, a test's ``AMIGO_SHARED``) must not trace and
#: compile every program again (that once cost a warm GPU fit 14 s).
TRACED_VARIABLES: dict[str, str] = {"AMIGO_JVP_BATCH": "8"}


def _environment() -> list[str]:
    """What besides the arguments decides the traced program."""
    return [
        f"format:{FORMAT}",
        f"source:{_source_digest()}",
        f"versions:{_versions()}",
        f"backend:{_device_platform()}",
        f"x64:{_config('jax_enable_x64')}",
        # Not the arithmetic, but what the program carries (amigo.runtime.short_locations).
        f"locations:{_config(LOCATIONS_OPTION)}",
        f"matmul:{_config('jax_default_matmul_precision')}",
        f"prng:{_config('jax_default_prng_impl')}",
        f"promotion:{_config('jax_numpy_dtype_promotion')}:{_config('jax_numpy_rank_promotion')}",
        *(
            f"{name}={os.environ.get(name, '').strip() or default}"
            for name, default in TRACED_VARIABLES.items()
        ),
    ]


# ------------------------------------------------------------------------ the store
#: A version's programs (a folder per source digest) unused this long are deleted when
#: another version first writes one: each release of amigo would otherwise leave its own.
STALE_DAYS = 7.0


def _folder() -> Path | None:
    """``cache_dir() / "programs" / <source digest>`` while JAX's compilation cache is on,
    else ``None``."""
    if not _config("jax_compilation_cache_dir"):
        return None
    return cache_dir() / "programs" / _source_digest()[:16]


@functools.cache
def _prune(folder: Path) -> None:
    """Delete the other versions' folders beside ``folder`` not written for
    :data:`STALE_DAYS` (once per process; best effort)."""
    import shutil
    import time

    cutoff = time.time() - STALE_DAYS * 86400.0
    try:
        for other in folder.parent.iterdir():
            if other != folder and other.is_dir() and other.stat().st_mtime < cutoff:
                shutil.rmtree(other, ignore_errors=True)
    except OSError:
        pass


def _write(path: Path, skeleton: str, blob: bytes) -> None:
    """Write atomically: concurrent runs write equivalent programs, the last rename wins."""
    temporary = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _prune(path.parent)
        handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        with os.fdopen(handle, "wb") as stream:
            header = skeleton.encode()
            stream.write(len(header).to_bytes(8, "little") + header + blob)
        os.replace(temporary, path)
    except OSError:  # a full or read-only disk: the program is only not kept
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)


def _read(path: Path) -> tuple[str, bytes] | None:
    """The output structure (JSON) and the serialized program of a file, or ``None``
    (absent, unreadable or damaged)."""
    try:
        data = path.read_bytes()
        size = int.from_bytes(data[:8], "little")
        return data[8 : 8 + size].decode(), data[8 + size :]
    except (OSError, UnicodeDecodeError):
        return None


#: Programs of this process by key and device: the deserialized export (compiled for the
#: device in effect: an executable is bound to its device) and its output's structure, or
#: ``None`` for a program that cannot be exported. Emptied by :func:`release`.
_LOADED: dict[str, tuple[Any, Any] | None] = {}
#: Held while a program is looked up, read or exported: threads that want the same
#: program at once (NUTS's chains, amigo.companions.posterior) read it once. Re-entrant:
#: an export traces functions that may ask for programs of their own.
_LOADING = threading.RLock()


def release() -> None:
    """Forget the programs held in memory (they are read again from disk if needed)."""
    _LOADED.clear()
    _DIGESTS.clear()


heap.holds_programs(release)  # a filter's or a posterior's programs go with JAX's own


def _caller(exported: Any) -> Callable[..., Any]:
    """The exported program, compiled (XLA's persistent cache has it after the first run).

    Compiled ahead of its call and kept without its exporter: a jitted ``Exported.call``
    would keep the program's lowered module beside the executable (~20 MB a program of
    the fit; 70 MB more at the peak of a three-filter fit, docs/performance.md)."""
    specs = [
        jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in exported.in_avals
    ]
    return jax.jit(exported.call).lower(*specs).compile()


# ---------------------------------------------------------------------- the wrapper
class _Program:
    """A function compiled by :func:`equinox.filter_jit`, its traced program kept on disk."""

    def __init__(self, function: Callable[..., Any]) -> None:
        self.function = function
        self.jitted = eqx.filter_jit(function)
        self.name = f"{function.__module__}:{function.__qualname__}"
        # A function outside amigo (a user's, a test's) is keyed on its own file too.
        source = inspect.getsourcefile(function)
        self.source = _file_digest(source) if source else "unknown"
        functools.update_wrapper(self, function)

    def __get__(self, instance: Any, owner: Any = None) -> Any:
        # A method: the instance is the first argument (a module, fingerprinted as such).
        return self if instance is None else functools.partial(self, instance)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        folder = _folder()
        if folder is None:
            return self.jitted(*args, **kwargs)
        leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
        if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
            return self.jitted(*args, **kwargs)  # inside a caller's trace: inlined
        try:
            key = self._key(treedef, leaves)
        except _Uncacheable as reason:
            _log.debug("%s: traced, not kept (%s)", self.name, reason)
            return self.jitted(*args, **kwargs)
        arrays = [leaf for leaf in leaves if eqx.is_array(leaf)]
        program = self._program(key, folder / f"{key}.bin", treedef, leaves)
        if program is None:
            return self.jitted(*args, **kwargs)
        caller, out_tree = program
        return jax.tree.unflatten(out_tree, caller(*arrays))

    def _key(self, treedef: Any, leaves: list[Any]) -> str:
        parts = [*_environment(), f"function:{self.name}:{self.source}", _structure_digest(treedef)]
        for leaf in leaves:
            if eqx.is_array(leaf):
                shape, dtype, weak = _aval(leaf)
                parts.append(f"array:{dtype.str}:{shape}:{weak}")
            else:
                _static(leaf, parts)  # a non-array leaf is static under filter_jit
        return hashlib.sha256("\n".join(parts).encode()).hexdigest()

    def _program(
        self, key: str, path: Path, treedef: Any, leaves: list[Any]
    ) -> tuple[Any, Any] | None:
        """The program of this key: held, read from disk, or traced and written."""
        with _LOADING:
            return self._program_locked(key, path, treedef, leaves)

    def _program_locked(
        self, key: str, path: Path, treedef: Any, leaves: list[Any]
    ) -> tuple[Any, Any] | None:
        held = f"{key}:{_config('jax_default_device')}"
        if held in _LOADED:
            return _LOADED[held]
        if path.with_suffix(".none").exists():
            _LOADED[held] = None
            return None
        stored = _read(path)
        if stored is not None:
            skeleton, blob = stored
            try:
                out_tree = jax.tree.structure(_decode(json.loads(skeleton)))
                program: tuple[Any, Any] | None = (
                    _caller(jax.export.deserialize(bytearray(blob))),
                    out_tree,
                )
            except Exception:  # a damaged file: trace again
                program = self._export(treedef, leaves, path)
        else:
            program = self._export(treedef, leaves, path)
        _LOADED[held] = program
        return program

    def _export(self, treedef: Any, leaves: list[Any], path: Path) -> tuple[Any, Any] | None:
        """Trace and lower the function at these arguments, keep it on disk."""
        is_array = [eqx.is_array(leaf) for leaf in leaves]
        statics = [None if flag else leaf for flag, leaf in zip(is_array, leaves, strict=True)]
        trees: list[Any] = []

        def flat(*arrays: Any) -> tuple[Any, ...]:
            it = iter(arrays)
            full = [next(it) if flag else s for flag, s in zip(is_array, statics, strict=True)]
            args, kwargs = jax.tree_util.tree_unflatten(treedef, full)
            outputs, out_tree = jax.tree_util.tree_flatten(self.jitted(*args, **kwargs))
            if not all(eqx.is_array(o) for o in outputs):
                raise _Uncacheable("a static output")
            trees.append(out_tree)
            return tuple(outputs)

        specs = []
        for leaf, flag in zip(leaves, is_array, strict=True):
            if flag:
                shape, dtype, weak = _aval(leaf)
                specs.append(jax.ShapeDtypeStruct(shape, dtype, weak_type=weak))
        try:
            # Exported for the platform it will run on (the default backend's, unless a
            # default device of another platform is set in this thread: latency_device).
            platform = _device_platform()
            platforms = None if platform == jax.default_backend() else [platform]
            exported = jax.export.export(jax.jit(flat), platforms=platforms)(*specs)
            out_tree = trees[-1]
            skeleton = json.dumps(_encode(out_tree))
            if jax.tree.structure(_decode(json.loads(skeleton))) != out_tree:
                return None  # a structure that does not read back the same: not kept
            blob = exported.serialize()
        except Exception as reason:  # not exportable: plain filter_jit from now on
            _log.debug("%s: not exportable (%r)", self.name, reason)
            _write(path.with_suffix(".none"), "", b"")  # later runs need not try again
            return None
        _write(path, skeleton, bytes(blob))
        return _caller(exported), out_tree


def jit(function: Callable[..., Any]) -> Callable[..., Any]:
    """:func:`equinox.filter_jit` whose traced program is kept on disk (module notes).

    Use it on functions called at the top level with concrete arguments; called while
    tracing, it is :func:`equinox.filter_jit` (inlined into the caller's program)."""
    if "<" in function.__qualname__:
        raise TypeError(f"programs.jit needs a module-level function, not {function.__qualname__}")
    return _Program(function)


# ------------------------------------------------------------------ side by side
def side_by_side(
    function: Callable[[Any], Any], items: Sequence[Any], workers: int | None = None
) -> list[Any]:
    """``[function(item) for item in items]``, the calls in threads: each in its own, or
    at most ``workers`` at a time (:func:`amigo.runtime.cores` for many small calls).

    For independent computations of compiled programs (NUTS's chains, chunks of a grid):
    XLA runs amigo's matrix products on one thread each (:mod:`amigo.runtime`), and a
    program of small operations barely keeps two cores busy; two of them side by side do
    (measured on a 2-core CPU: docs/performance.md, "Work side by side"). Each call's
    results are waited for in its thread, so a caller gets finished arrays. The calls
    share only their inputs, which they must not change: their results are the same bits
    as one after the other. The calling thread's ``jax.enable_x64`` and
    ``jax.default_device`` (per-thread settings) hold in every thread. One item or none:
    called in this thread.
    """
    items = list(items)
    if len(items) < 2:
        return [function(item) for item in items]
    x64 = bool(_config("jax_enable_x64"))
    device = _config("jax_default_device")

    def run(item: Any) -> Any:
        with jax.enable_x64(x64), jax.default_device(device):
            return jax.block_until_ready(function(item))

    from concurrent.futures import ThreadPoolExecutor

    threads = min(len(items), workers or len(items))
    with ThreadPoolExecutor(threads, thread_name_prefix="amigo") as pool:
        return list(pool.map(run, items))
