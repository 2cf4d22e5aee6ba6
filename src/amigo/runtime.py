"""XLA settings that amigo makes before JAX starts: the same inputs give the same bits,
and the CPU compiles faster.

A fit takes discrete decisions (accept a step, take one more chord step, stop) on
float32 numbers, so a difference in the last bit of one gradient can move its optimum by
a few hundredths of a sigma and change the products' printed numbers. On the CPU, XLA's
matrix products run on a pool of threads (Eigen's), and a product run that way is not
always bitwise reproducible: on a 2-core CPU under load, the first evaluation of a fit's
gradient in a new process differed in its last bits from the later ones (same inputs,
same compiled program) in 2 of 16 fits started two at a time (2026-11-27; ``amigo run
--manifest`` then gave a target's products 0.05 sigma away from a serial run's). With the
products computed on one thread each, 30 of 30 such fits gave identical bits. The other
parallel parts of a program (its loops and fusions) still use every core. On 2 cores
this costs no time (docs/performance.md); on a many-core CPU the products may be slower:
``XLA_FLAGS=--xla_cpu_multi_thread_eigen=true`` trades the reproducibility back.

Compilation is most of a cold run's time on a CPU. XLA's CPU back end emits its fused
loops with its newer MLIR "fusion emitters" by default; its older emitters compile the
same programs in about three quarters of the time, and the programs run as fast
(measured 2026-11-27 on a 2-core AMD EPYC, jaxlib 0.10.2: a small level-2 fit's
instrument-block Jacobian compiled in 7-8 s instead of 10-12 s, a whole cold ``amigo fit``
90 -> 64 s, the warm fit 18.1 -> 17.1 s, the z-scores the same to five digits).
:func:`fast_cpu_compile` asks for the older emitters, only with the jaxlib versions where
the flag was measured: XLA stops the process on a flag it does not know. It also lowers
the LLVM back end's optimisation level from 3 to 1 (measured 2026-11-28, same machine
and jaxlib, fresh caches: the tests' small level-2 fit compiled in 33 s instead of 44-45
s, its warm run 35-40 s either way; a real F480M fit of COM 1093, cold 177 s either way,
compile 56 -> 50 s, run 122 -> 127 s, warm 113 -> 111 s, its products within 0.04 sigma
of the default's), but only where no accelerator's plugin is installed: the flag is not
the CPU's alone, and a GPU's kernels were not measured with it.

Programs carry one source line per operation, not a Python traceback
(:func:`short_locations`). JAX writes every operation's traceback, up to 100 frames, into
the program's locations, and XLA's GPU back end formats them into its profiling
annotations each time it loads an executable, also from its persistent cache. In a warm
three-filter ``amigo fit`` on an H200 (2026-11-30, JAX 0.11.2), reading programs from the
cache took 10.5 s of py-spy's 45.8 s of samples (13.0 s in ``benchmarks/profile_fit.py``'s
compile column), and in native samples of another warm fit (cut short) 14.1 of the 23.4 s
spent loading programs were in ``xla::gpu::ModuleAnnotations``, most of them formatting
stack frames. With one line per operation the largest program's callsite locations go
from 361 to 0; on the CPU (fresh caches) the products are the same to every printed digit
(AB Dor, three filters) and the warm fit's time reading programs is 3.0 s either way.
What it saves on a GPU is not measured yet. JAX's persistent cache keys a program
without its locations: the two settings keep their compiled programs in folders of their
own (:func:`amigo.cachedir.full_tracebacks`, :func:`amigo.cachedir.enable_compilation_cache`),
unless ``JAX_COMPILATION_CACHE_DIR`` names one folder for both.

This module imports neither JAX nor NumPy, so that the command line can set the flags
before JAX reads its environment.
"""

from __future__ import annotations

import os
import sys

#: XLA's CPU flag for multi-threaded matrix products (its default: on).
EIGEN_THREADS_FLAG = "--xla_cpu_multi_thread_eigen"
#: XLA's CPU flag for the MLIR fusion emitters (its default: on).
FUSION_EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters"
#: jaxlib versions (major, minor) whose XLA knows FUSION_EMITTERS_FLAG, as measured.
FUSION_EMITTERS_JAXLIB = ((0, 10),)
#: XLA's optimisation level of its LLVM back end (its default: 3), CPU and GPU alike.
OPT_LEVEL_FLAG = "--xla_backend_optimization_level"


def configure_xla() -> bool:
    """The settings of this module (:func:`reproducible_cpu`, :func:`fast_cpu_compile`,
    :func:`short_locations`); whether the first applies (no JAX backend started yet)."""
    fast_cpu_compile()
    short_locations()
    return reproducible_cpu()


#: JAX's option (and, upper case, its environment variable) for full tracebacks in the
#: programs' locations (the same as :data:`amigo.cachedir.LOCATIONS_OPTION`, which picks
#: the compiled programs' folder by it; the foundation's modules do not import each other).
LOCATIONS_OPTION = "jax_include_full_tracebacks_in_locations"


def short_locations() -> None:
    """Programs carry each operation's own source line, not its whole traceback (module
    notes): ``JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS=false`` before JAX starts, unless
    the user set it (a user's choice wins) or JAX is imported already (a library user's
    process keeps its own setting)."""
    if LOCATIONS_OPTION.upper() in os.environ or "jax" in sys.modules:
        return
    os.environ[LOCATIONS_OPTION.upper()] = "false"


def fast_cpu_compile() -> bool:
    """Compile with XLA's older CPU fusion emitters (see module notes).

    Appends ``--xla_cpu_use_fusion_emitters=false`` to ``XLA_FLAGS`` unless the flag is
    there already (a user's choice wins) or the installed jaxlib is not one of
    :data:`FUSION_EMITTERS_JAXLIB`; with it, ``--xla_backend_optimization_level=1``
    unless an accelerator's JAX plugin is installed (:func:`_accelerator_plugin`).
    Each flag a user set keeps the user's value. Returns whether the emitters' flag is
    now in ``XLA_FLAGS``.
    """
    if _jaxlib_minor() in FUSION_EMITTERS_JAXLIB:
        _default_flag(FUSION_EMITTERS_FLAG, "false")
        if not _accelerator_plugin():
            _default_flag(OPT_LEVEL_FLAG, "1")
    return FUSION_EMITTERS_FLAG in os.environ.get("XLA_FLAGS", "")


def _accelerator_plugin() -> bool:
    """Whether a JAX back end for an accelerator is installed: the CUDA and ROCm plugins
    live in the ``jax_plugins`` namespace package, the TPU's in ``libtpu`` (no import)."""
    from importlib.util import find_spec

    return any(find_spec(name) is not None for name in ("jax_plugins", "libtpu"))


def _default_flag(name: str, value: str) -> None:
    """Append ``name=value`` to ``XLA_FLAGS`` unless ``name`` is there (a user's wins)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if name not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {name}={value}".strip()


def _jaxlib_minor() -> tuple[int, int] | None:
    """(major, minor) of the installed jaxlib, read from its metadata (no import)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (PackageNotFoundError, ValueError):
        return None


def reproducible_cpu() -> bool:
    """Run XLA's CPU matrix products on one thread each (see module notes).

    Appends ``--xla_cpu_multi_thread_eigen=false`` to ``XLA_FLAGS`` unless the flag is
    there already (a user's explicit choice wins). JAX reads ``XLA_FLAGS`` once, when
    its first computation starts a backend: returns whether the setting applies, i.e.
    no backend has started yet in this process.
    """
    _default_flag(EIGEN_THREADS_FLAG, "false")
    return not _backend_started()


def _backend_started() -> bool:
    """Whether JAX has started a backend in this process (then ``XLA_FLAGS`` is read)."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
    except ImportError:  # a JAX without this private module: assume the worst
        return True
    return bool(getattr(xla_bridge, "_backends", None))


def cores() -> int:
    """The CPU cores this process may run on: its affinity (a batch job's share, ``taskset``),
    not the machine's count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity on this platform (macOS)
        return max(1, os.cpu_count() or 1)


#: Where latency-bound programs (NUTS's chains) run when JAX's default backend is an
#: accelerator: ``host`` (the CPU) or ``default`` (the accelerator;
#: :func:`amigo.programs.latency_device`, docs/performance.md "On a GPU, a sixth time").
SAMPLER_DEVICE_VARIABLE = "AMIGO_SAMPLER_DEVICE"
SAMPLER_DEVICE_CHOICES = ("default", "host")


def sampler_device_setting() -> str:
    """``AMIGO_SAMPLER_DEVICE`` (``default`` when unset); ``ValueError`` for another value."""
    choice = os.environ.get(SAMPLER_DEVICE_VARIABLE, "").strip() or SAMPLER_DEVICE_CHOICES[0]
    if choice not in SAMPLER_DEVICE_CHOICES:
        raise ValueError(f"{SAMPLER_DEVICE_VARIABLE} is {choice!r}: expected 'default' or 'host'")
    return choice
