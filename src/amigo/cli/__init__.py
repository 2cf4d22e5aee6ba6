"""The ``amigo`` command line.

Each sub-command lives in its own module of this package and is imported only when it
runs, so ``amigo info`` starts in a fraction of a second without importing JAX. To add a
command, write ``amigo/cli/<name>.py`` with a :func:`click.command` called ``command`` and
list it in :data:`COMMANDS`.

Exit status (see docs/interfaces): 0 success, 2 bad input or usage (one line on stderr, no
traceback), 1 unexpected internal error, 3 and 4 some or all of a fit's filters without
products (:mod:`amigo.pipeline.outcome`), 130 interrupted.
"""

from __future__ import annotations

import atexit
import importlib
import os
import signal
import sys
import threading
from typing import Any, NoReturn

import click

from amigo._version import __version__
from amigo.cachedir import enable_compilation_cache
from amigo.errors import InputError, NumericalFailure, ReportedInputError
from amigo.runtime import configure_xla

#: command name -> (module under amigo.cli, one-line help shown in ``amigo --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("amigo.cli.info", "Identify and validate JWST NIRISS AMI files."),
    "simulate": ("amigo.cli.simulate", "Simulate raw AMI ramps with physical detector effects."),
    "process": ("amigo.cli.process", "Raw ramps (uncal) -> slopes and covariances (calslope)."),
    "fit": ("amigo.cli.fit", "Fit exposures and extract calibrated observables (DISCOs)."),
    "basis": ("amigo.cli.basis", "Build and cache the latent visibility bases."),
    "detect": ("amigo.cli.detect", "Search calibrated observables for companions; limits."),
    "run": ("amigo.cli.run", "Raw ramps to companions: process + fit + detect in one go."),
    "demo": ("amigo.cli.demo", "The whole job on built-in simulated data (a binary)."),
    "train": (
        "amigo.cli.train",
        "Train the base model (instrument + BFE network) on calibration data.",
    ),
}


class _LazyGroup(click.Group):
    """A click group whose sub-commands are imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        module = importlib.import_module(COMMANDS[cmd_name][0])
        return module.command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Show the short help without importing every command module.
        with formatter.section("Commands"):
            formatter.write_dl([(name, text) for name, (_, text) in COMMANDS.items()])


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="amigo")
def cli() -> None:
    """amigo: JWST NIRISS aperture masking interferometry, from pixels to planets."""


def fail_input(error: InputError) -> None:
    """Print one line for a bad input and exit with status 2."""
    click.echo(f"amigo: error: {error}", err=True)
    sys.exit(2)


def usage_line(error: click.ClickException) -> str:
    """Click's message as the interface's one line, with where to read the usage:
    ``amigo fit: error: Missing option '--cal'. (amigo fit -h: usage)``. Click itself
    prints the usage, a hint and a blank line before its message."""
    ctx = getattr(error, "ctx", None)
    where = ctx.command_path if ctx is not None else "amigo"
    message = " ".join(error.format_message().split())
    hint = f" ({where} -h: usage)" if isinstance(error, click.UsageError) else ""
    return f"{where}: error: {message}{hint}"


def main(argv: list[str] | None = None) -> Any:
    """Entry point of the ``amigo`` console script."""
    # The same inputs give the same products, bit for bit, the CPU compiles faster and
    # programs carry one source line per operation (amigo.runtime): first, since the
    # compiled programs' folder depends on the last.
    configure_xla()
    # Compiled programs are kept between runs (amigo.cachedir): the second fit of the same
    # shapes skips the compilation, most of a cold run's time on a CPU.
    enable_compilation_cache()
    # SIGTERM (a batch system's kill, a closed terminal) as Ctrl-C: the finally clauses run,
    # so no temporary product is left behind (SIGKILL cannot be caught; amigo.io.atomic's
    # temporary files are then hidden names no command reads). Restored on return, for
    # callers in Python.
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        return _run(argv)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def console() -> NoReturn:
    """Entry point of the ``amigo`` console script and of ``python -m amigo``: :func:`main`,
    then out of the process without the interpreter's teardown.

    A normal exit runs JAX's exit handler (its compiled programs and buffers released one
    by one) and then frees every object the run made: 2.0 s from the last product of a
    simulated F480M fit to the process's end, 1.4-1.8 s after a detection (2-core AMD
    EPYC, 2026-12-02; 0.1 s without), for a process that ends anyway. Every
    product is written and closed by then (amigo.io.atomic), so what is skipped is only
    memory handed back. Kept: the streams' buffers are flushed, threads still running are
    waited for, and every other exit handler runs (logging's, a Dask cluster's). Callers in
    Python call :func:`main`, whose ``SystemExit`` they can catch; ``AMIGO_DEBUG``'s
    traceback leaves the usual way.
    """
    try:
        main()
        status = 0
    except SystemExit as done:
        status = _exit_status(done.code)
    _leave(status)


def _exit_status(code: object) -> int:
    """The status ``sys.exit(code)`` would give: ``None`` 0, an int itself, anything else
    printed to stderr and 1 (Python's own rule)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _leave(status: int) -> NoReturn:
    """Exit with ``status`` after what a normal exit does that matters (see :func:`console`),
    without JAX's clean-up and the interpreter's freeing of its objects."""
    for thread in threading.enumerate():  # what the interpreter waits for at exit
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    jax_api = sys.modules.get("jax._src.api")
    clean_up = getattr(jax_api, "clean_up", None)
    if clean_up is not None:
        atexit.unregister(clean_up)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more to say
            pass
    os._exit(status)


def _run(argv: list[str] | None) -> Any:
    """The command, with every failure turned into its one line and exit status."""
    try:
        # The arguments as given travel in the context: a command that records how it was
        # run (amigo train) reads them there, whether a console script or a caller in
        # Python invoked it.
        args = list(sys.argv[1:] if argv is None else argv)
        # Not click's standalone mode: it would turn Ctrl-C into "Aborted!" and status 1.
        result = cli.main(args=args, prog_name="amigo", standalone_mode=False, obj={"argv": args})
        sys.exit(result if isinstance(result, int) else 0)
    except click.exceptions.NoArgsIsHelpError as error:  # "amigo" alone: the help itself
        error.show()
        sys.exit(error.exit_code)
    except click.ClickException as error:  # usage errors: status 2, one line
        click.echo(usage_line(error), err=True)
        sys.exit(error.exit_code)
    except ReportedInputError:
        sys.exit(2)
    except InputError as error:
        fail_input(error)
    except NumericalFailure as error:  # a computation without a result, outside a filter
        from amigo.pipeline.outcome import EXIT_NO_PRODUCT

        click.echo(f"amigo: failed: {error}", err=True)
        sys.exit(EXIT_NO_PRODUCT)
    except (KeyboardInterrupt, click.exceptions.Abort):
        click.echo("amigo: interrupted", err=True)
        sys.exit(130)
    except OSError as error:
        from amigo.io.atomic import OUTPUT_ERRNOS, unwritable

        if error.errno not in OUTPUT_ERRNOS or os.environ.get("AMIGO_DEBUG"):
            _internal_error(error)
        # An output folder that cannot be made or written (amigo.io.atomic covers files).
        fail_input(unwritable(error.filename, error))
    except Exception as error:
        _internal_error(error)


def _terminated(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _internal_error(error: BaseException) -> None:
    """A bug of amigo, not of the input: one line and exit status 1 (``AMIGO_DEBUG=1``:
    the traceback instead)."""
    if os.environ.get("AMIGO_DEBUG"):
        raise error
    click.echo(
        f"amigo: internal error: {type(error).__name__}: {error} "
        "(set AMIGO_DEBUG=1 for a traceback, and please report it)",
        err=True,
    )
    sys.exit(1)
