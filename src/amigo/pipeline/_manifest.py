"""The work of ``amigo run --manifest`` (:func:`amigo.pipeline.run_manifest`): many targets
in parallel on Dask distributed.

Each target of the manifest (:mod:`amigo.io.manifest`) is one task: raw ramps go through
:func:`~amigo.pipeline.run` (process, fit, detect), level-2 or calslope files through
:func:`~amigo.pipeline.fit` and :func:`~amigo.pipeline.detect`, into ``OUT/<name>/``.
Tasks run on a local cluster of worker processes (``workers``) or on an existing Dask
scheduler (``scheduler``: a dask-jobqueue cluster on an HPC system, say); every worker
imports amigo, and compiled programs and latent bases are shared through the cache
folder (:mod:`amigo.cachedir`), so a worker's second target compiles nothing.

Restart-safe: a target that finished writes ``OUT/<name>/target.json`` last (its inputs'
fingerprints, options, version and exit status). A later run skips every target whose
record says it finished with status 0 for the same inputs and options; the others start
again, and their own steps keep what an earlier run left complete (calslope files, fitted
filters, the search). A target that fails is recorded (``failed``, with its one-line
reason) and does not stop the others. ``OUT/manifest_summary.json`` holds the table.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from amigo import runtime
from amigo.errors import AmigoError, InputError
from amigo.io.manifest import Target, read_manifest

#: The record a finished target leaves in its folder (written last).
TARGET_RECORD = "target.json"
#: The table of a manifest run, in OUT.
SUMMARY = "manifest_summary.json"
#: The thread counts Dask caps in its workers (see :class:`_client`).
BLAS_THREADS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
#: A target's raw ramps are processed with amigo run, its other files fitted as they are:
#: one target is one or the other.
MIXED_RAW = "mixes raw ramps (_uncal) with level-2 or calslope files"
#: Options of :func:`run_manifest`'s callers that apply to every target (the command line's).
DEFAULTS: dict[str, Any] = {
    "model": None,
    "detector": None,
    "knots": None,
    "knot_spacing": None,
    "rmax_mas": 1000.0,
    "step_mas": None,
    "hmc": True,
    "first_group": True,
}


@dataclass(frozen=True)
class TargetOutcome:
    """What happened to one target.

    Attributes
    ----------
    name
        The target's name (its folder under OUT).
    state
        ``"done"`` (ran to the end, in this call), ``"skipped"`` (finished by an earlier
        run for the same inputs and options) or ``"failed"``.
    status
        The run's exit status (0, 3 or 4 as ``amigo run``; 2 bad input, 1 other failure).
    seconds
        Wall time of the target in this call (0 when skipped).
    companions
        Companions detected (``None`` when the run has no search).
    message
        Why it failed (one line), else empty.
    """

    name: str
    state: str
    status: int
    seconds: float
    companions: int | None
    message: str = ""


@dataclass
class ManifestResult:
    """What :func:`run_manifest` did: the targets' outcomes in the manifest's order."""

    out: Path
    outcomes: list[TargetOutcome]

    @property
    def status(self) -> int:
        """0 when every target finished with status 0; 3 when some did not; 4 when none
        did (the exit statuses of ``amigo fit``)."""
        from amigo.pipeline.outcome import EXIT_NO_PRODUCT, EXIT_PARTIAL

        good = [o.status == 0 and o.state != "failed" for o in self.outcomes]
        if all(good):
            return 0
        return EXIT_PARTIAL if any(good) else EXIT_NO_PRODUCT

    def table(self) -> str:
        """The outcomes as a plain-text table (what ``amigo run --manifest`` prints)."""
        width = max([len("target"), *(len(o.name) for o in self.outcomes)])
        lines = [f"{'target':{width}s}  {'state':7s}  exit  {'seconds':>8s}  companions  note"]
        for o in self.outcomes:
            found = "-" if o.companions is None else str(o.companions)
            lines.append(
                f"{o.name:{width}s}  {o.state:7s}  {o.status:4d}  {o.seconds:8.1f}  "
                f"{found:>10s}  {o.message}"
            )
        return "\n".join(lines)


def _settings(target: Target, defaults: Mapping[str, Any]) -> dict[str, Any]:
    """The target's options: the manifest's over the caller's over :data:`DEFAULTS`."""
    return {**DEFAULTS, **{k: v for k, v in defaults.items() if k in DEFAULTS}, **target.options}


def _identity(target: Target, settings: Mapping[str, Any]) -> dict[str, Any]:
    """What a finished target's record must match for a rerun to skip it."""
    from amigo._version import __version__
    from amigo.io.files import fingerprint

    def files(paths: tuple[Path, ...]) -> list[list[str]]:
        return [[p.name, fingerprint(p)] for p in paths]

    return {
        "version": __version__,
        "settings": dict(settings),
        "sci": files(target.sci),
        "cal": files(target.cal),
        "superbias": files(target.superbias),
    }


def _record(target: Target, out: Path) -> dict[str, Any] | None:
    """The ``target.json`` an earlier run left in ``out/<name>/`` (``None``: none, or
    unreadable)."""
    try:
        record = json.loads((out / target.name / TARGET_RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def finished(target: Target, out: Path, defaults: Mapping[str, Any]) -> bool:
    """Whether ``out/<name>/target.json`` says an earlier run finished this target with
    status 0 for the same inputs, options and amigo version."""
    record = _record(target, out)
    if record is None or record.get("status") != 0:
        return False
    try:
        identity = _identity(target, _settings(target, defaults))
    except OSError:  # an input gone since the manifest was read
        return False
    return record.get("identity") == identity


def run_target(
    target: Target, out: Path, defaults: Mapping[str, Any], force: bool
) -> TargetOutcome:
    """Run one target into ``out/<name>/`` (in a Dask worker, or here): never raises.

    Raw ramps: :func:`~amigo.pipeline.run`; level-2 or calslope files:
    :func:`~amigo.pipeline.fit` then :func:`~amigo.pipeline.detect`. On success the target's
    record is written last, atomically.
    """
    from amigo.io.atomic import write_text
    from amigo.io.jwst import data_kind

    start = time.perf_counter()
    folder = out / target.name
    settings = _settings(target, defaults)
    try:
        kinds = {data_kind(p) for p in (*target.sci, *target.cal)}
        if kinds == {"uncal"}:
            from amigo.pipeline._run import run

            result = run(target.sci, target.cal, folder, superbias=target.superbias,
                         force=force, **settings)  # fmt: skip
            status, search = result.status, result.detect
        elif "uncal" in kinds:
            raise InputError(None, MIXED_RAW)
        else:
            status, search = _fit_and_detect(target, folder, settings, force)
        companions = None if search is None else len(search.companions)
        identity = _identity(target, settings)
        record = {"identity": identity, "status": status, "companions": companions}
        write_text(folder / TARGET_RECORD, json.dumps(record, indent=1) + "\n")
        state, message = "done", ""
    except AmigoError as error:  # a bad input or a numerical failure: one line
        status, companions, state, message = 2, None, "failed", str(error)
    except Exception as error:  # anything else must not stop the other targets
        last = traceback.extract_tb(error.__traceback__)[-1]
        where = f"{Path(last.filename).name}:{last.lineno}"
        status, companions, state = 1, None, "failed"
        message = f"{type(error).__name__}: {error} ({where})".replace("\n", " ")
    return TargetOutcome(
        target.name, state, status, time.perf_counter() - start, companions, message
    )


def _fit_and_detect(target: Target, folder: Path, settings: Mapping[str, Any], force: bool):
    """amigo fit then amigo detect of a target of level-2 or calslope files."""
    from amigo.pipeline._detect import detect
    from amigo.pipeline._fit import fit
    from amigo.pipeline._run import one_science_target

    one_science_target(tuple(map(Path, target.sci)))
    fitted = fit(
        target.sci,
        target.cal,
        folder,
        model=settings["model"],
        detector=settings["detector"],
        knots=settings["knots"],
        knot_spacing=settings["knot_spacing"],
        superbias=target.superbias,
        first_group=settings["first_group"],
        force=force,
        keep_products=False,
    )
    if not fitted.calvis:
        return fitted.status, None
    search = detect(
        fitted.calvis,
        folder,
        rmax_mas=settings["rmax_mas"],
        step_mas=settings["step_mas"],
        hmc=settings["hmc"],
        force=force,
    )
    return fitted.status, search


def default_workers(n_targets: int) -> int:
    """Local workers when none are asked for: one per two of the CPU cores this process
    may run on (:func:`amigo.runtime.cores`: a batch job's share, not the machine's count;
    each worker's XLA runs its own threads), at least one, at most one per target."""
    return max(1, min(n_targets, runtime.cores() // 2))


def check_target(manifest: Path, target: Target, defaults: Mapping[str, Any]) -> None:
    """A target's options and inputs as :func:`amigo.pipeline.run` checks them before any
    work, for every target before the first runs: a mistake in the manifest is one line
    naming it and the target (:class:`~amigo.errors.InputError`), not a failed target
    found an hour later."""
    from amigo.pipeline._run import check_before_work

    o = _settings(target, defaults)
    try:
        kinds = check_before_work(
            target.sci, target.cal, o["model"], o["detector"], o["knots"], o["knot_spacing"],
            o["rmax_mas"], o["step_mas"],
        )  # fmt: skip
        if "uncal" in kinds.values() and set(kinds.values()) != {"uncal"}:
            raise InputError(None, MIXED_RAW)  # as run_target would, after the others ran
    except InputError as error:
        raise InputError(manifest, f"target {target.name}: {error}") from None


def run_manifest(
    manifest: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    **defaults: Any,
) -> ManifestResult:
    """Run every target of ``manifest`` into ``out/<name>/`` on Dask distributed, as
    ``amigo run --manifest``.

    ``workers``: worker processes of a local cluster (default :func:`default_workers`);
    ``scheduler``: the address of an existing Dask scheduler instead (``tcp://host:8786``);
    ``force``: run finished targets again; ``defaults``: options for every target
    (:data:`DEFAULTS`; the manifest's own override them). Writes ``out/manifest_summary.json``
    and returns the outcomes; a target's failure is an outcome, not an exception.
    """
    from amigo.io.atomic import write_text
    from amigo.progress import step, track

    unknown = sorted(set(defaults) - set(DEFAULTS))
    if unknown:
        raise TypeError(f"run_manifest() got unknown options {unknown}")
    if workers is not None and workers < 1:
        raise InputError(None, f"--workers must be at least 1, not {workers}")
    targets = read_manifest(manifest)
    for target in targets:
        check_target(Path(manifest), target, defaults)
    out = Path(out)
    outcomes: dict[str, TargetOutcome] = {}
    todo = []
    for target in targets:
        if not force and finished(target, out, defaults):
            outcomes[target.name] = TargetOutcome(
                target.name, "skipped", 0, 0.0, _found(out, target)
            )
        else:
            todo.append(target)
    step(
        f"run: {len(targets)} targets, {len(targets) - len(todo)} finished earlier, {len(todo)} to run"
    )
    if todo:
        with _client(workers or default_workers(len(todo)), scheduler) as client:
            futures = {
                client.submit(run_target, t, out, defaults, force, pure=False): t for t in todo
            }
            from dask.distributed import as_completed

            done = 0
            for future in track(as_completed(futures), "run: targets", total=len(futures)):
                target = futures[future]
                try:
                    outcome = future.result()
                except Exception as error:  # the worker died (memory, a signal): KilledWorker
                    outcome = TargetOutcome(
                        target.name, "failed", 1, 0.0, None, f"{type(error).__name__}: {error}"
                    )
                outcomes[target.name] = outcome
                done += 1
                note = f": {outcome.message}" if outcome.message else ""
                step(
                    f"run: [{done}/{len(futures)}] {target.name} {outcome.state} (exit "
                    f"{outcome.status}, {outcome.seconds:.0f} s){note}"
                )
    result = ManifestResult(out, [outcomes[t.name] for t in targets])
    summary = {
        "manifest": str(Path(manifest).resolve()),
        "status": result.status,
        "targets": [asdict(o) for o in result.outcomes],
    }
    write_text(out / SUMMARY, json.dumps(summary, indent=1) + "\n")
    return result


def _found(out: Path, target: Target) -> int | None:
    """Companions recorded by a finished target."""
    found = (_record(target, out) or {}).get("companions")
    return found if isinstance(found, int) else None


class _client:
    """A Dask client on a new local cluster of ``workers`` processes, or on ``scheduler``;
    closed (and the local cluster shut down) on exit."""

    def __init__(self, workers: int, scheduler: str | None) -> None:
        self.workers, self.scheduler = workers, scheduler

    def __enter__(self):
        import logging

        from dask.distributed import Client, LocalCluster

        from amigo.progress import step

        if self.scheduler is not None:
            try:
                self.cluster = None
                self.client = Client(self.scheduler, timeout="30s")
            except (OSError, TimeoutError) as error:
                raise InputError(None, f"no Dask scheduler at {self.scheduler} ({error})") from None
            step(f"run: on the Dask scheduler at {self.scheduler}")
            return self.client
        import dask

        # Dask caps a worker's BLAS at one thread; NumPy's linear algebra then rounds
        # differently from a serial amigo run (DISCOs 1e-9 apart): the workers get this
        # process's setting instead, so that a target's products do not depend on where
        # it ran.
        environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
        for name in BLAS_THREADS:
            environ.pop(name, None)
            if name in os.environ:
                environ[name] = os.environ[name]
        # One task thread per worker: a target is one long task, and JAX runs its own.
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
            self.cluster = LocalCluster(
                n_workers=self.workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
        self.client = Client(self.cluster)
        step(f"run: a local Dask cluster of {self.workers} worker process(es)")
        return self.client

    def __exit__(self, *exc: object) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
