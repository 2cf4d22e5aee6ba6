"""Where a command's time goes: XLA compilation per compiled function, against the wall.

On a CPU most of a cold ``amigo`` run is compilation (a Jacobian of the model compiles
for minutes on 2 cores). This runs one ``amigo`` command in this process with JAX's
compile log on and prints a table: for every compiled function, how many times it was
compiled (float32 and float64 apart), and the seconds spent in XLA's compiler; then the
total against the wall time. Element-wise operations evaluated outside any ``jit`` show up
as ``jit(multiply)`` and the like: each is one program.

    python benchmarks/compile_time.py [--top 25] [--no-cache] -- demo --out /tmp/demo --no-hmc

``--no-cache`` turns the persistent compilation cache off (a cold run); by default the
command uses it as a user's run does (``amigo.cachedir``). A second table sums JAX's own
duration events over the run: tracing to jaxprs, lowering to StableHLO, XLA compilation,
and reading compiled programs from the persistent cache; run the command twice to see
what a new process pays with the cache warm (tracing and lowering are paid in every
process: the cache is keyed by the lowered program).
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import re
import sys
import time
from collections import defaultdict

os.environ.setdefault("JAX_PLATFORMS", "cpu")

_FINISHED = re.compile(r"Finished XLA compilation of (\S+) in ([0-9.eE+-]+) sec")
_STARTED = re.compile(r"Compiling (\S+) with global shapes and types \((.*)")


class CompileLog(logging.Handler):
    """Collects (function, precision) -> [count, seconds] from JAX's compile log."""

    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.table: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0, 0.0])
        self._precision: dict[str, str] = {}

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        started = _STARTED.match(message)
        if started:
            self._precision[started.group(1)] = "f64" if "float64" in started.group(2) else "f32"
            return
        finished = _FINISHED.match(message)
        if finished:
            name = finished.group(1)
            row = self.table[(name, self._precision.get(name, "?"))]
            row[0] += 1
            row[1] += float(finished.group(2))


#: JAX's duration events (``jax.monitoring``) and what the table calls them.
STAGE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "tracing (Python -> jaxpr)",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lowering (jaxpr -> StableHLO)",
    "/jax/core/compile/backend_compile_duration": "XLA compilation or loading",
    "/jax/compilation_cache/cache_retrieval_time_sec": "persistent cache reads",
}


class StageDurations:
    """Sums (count, seconds) of the events of :data:`STAGE_EVENTS`."""

    def __init__(self) -> None:
        self.table: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])

    def __call__(self, event: str, duration_secs: float, **_: str | int) -> None:
        if event in STAGE_EVENTS:
            row = self.table[event]
            row[0] += 1
            row[1] += duration_secs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=25, help="rows of the table")
    parser.add_argument("--no-cache", action="store_true", help="no persistent cache")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- amigo arguments")
    args = parser.parse_args()
    command = [a for a in args.command if a != "--"] or ["demo", "--out", "/tmp/demo"]
    if args.no_cache:
        os.environ["JAX_COMPILATION_CACHE_DIR"] = ""

    import jax
    import jax.monitoring

    from amigo.cli import main as amigo

    durations = StageDurations()
    jax.monitoring.register_event_duration_secs_listener(durations)

    jax.config.update("jax_log_compiles", True)
    log = CompileLog()
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler"):
        logger = logging.getLogger(name)
        logger.addHandler(log)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False  # the table, not thousands of log lines
    start = time.perf_counter()
    try:
        amigo(command)
    except SystemExit as exit_:
        if exit_.code not in (0, None):
            raise
    wall = time.perf_counter() - start

    rows = sorted(log.table.items(), key=lambda item: -item[1][1])
    total = sum(seconds for _, seconds in log.table.values())
    count = int(sum(n for n, _ in log.table.values()))
    print(f"\namigo {' '.join(command)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, JAX {jax.__version__}, "
          f"{jax.devices()[0].platform}")  # fmt: skip
    print(f"{'compiled function':40s} {'dtype':>5s} {'times':>6s} {'seconds':>9s}")
    for (name, precision), (n, seconds) in rows[: args.top]:
        print(f"{name:40s} {precision:>5s} {int(n):6d} {seconds:9.1f}")
    rest = rows[args.top :]
    if rest:
        n_rest = int(sum(n for _, (n, _) in rest))
        s_rest = sum(s for _, (_, s) in rest)
        print(f"{'(the others)':40s} {'':>5s} {n_rest:6d} {s_rest:9.1f}")
    print(f"{'compilation, all':40s} {'':>5s} {count:6d} {total:9.1f}")
    print(f"{'wall time of the command':40s} {'':>5s} {'':>6s} {wall:9.1f}")
    print(f"\n{'JAX stage':40s} {'':>5s} {'events':>6s} {'seconds':>9s}")
    for event, label in STAGE_EVENTS.items():
        n, seconds = durations.table.get(event, (0, 0.0))
        print(f"{label:40s} {'':>5s} {int(n):6d} {seconds:9.1f}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
