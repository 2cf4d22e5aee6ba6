"""Single source of the package version (read by pyproject and written into every product)."""

from pathlib import Path

__version__ = "0.1.0"


def source_commit() -> str | None:
    """The git commit of the amigo source tree this process runs (``None`` when amigo is
    not run from a git checkout, e.g. an installed wheel), with ``+dirty`` when the tree
    has uncommitted changes: a model's record names the code that trained it."""
    import subprocess

    root = Path(__file__).resolve().parents[2]  # src/amigo/_version.py -> the checkout
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
        status = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{commit}+dirty" if status else commit
