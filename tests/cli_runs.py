"""Running ``amigo`` from tests: in this process (exit status returned) or as a child
process (to interrupt it)."""

from __future__ import annotations

import os
import subprocess
import sys


def amigo_status(args: list[str]) -> int:
    """Run ``amigo ARGS`` in this process; its exit status."""
    from amigo.cli import main

    try:
        main(args)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    return 0


def amigo_child(*args: object, **popen: object) -> subprocess.Popen:
    """Start ``python -m amigo ARGS`` on the CPU, stdout and stderr captured as text."""
    return subprocess.Popen(
        [sys.executable, "-m", "amigo", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        **popen,
    )
