"""The documentation site builds with every warning an error (``mkdocs build --strict``).

The build renders the API reference from the docstrings (a docstring mkdocstrings
cannot render fails it), checks every link and anchor between pages, and draws the
gallery's figures with amigo's plotting functions (docs/hooks/gallery.py), so it also
tests that those still run.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None,
    reason="mkdocs is not installed (pip install -e '.[test]' brings it)",
)
def test_docs_build_strict(tmp_path):
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", JAX_PLATFORMS="cpu", MPLBACKEND="Agg")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stderr[-6000:]}"
    # Every figure the gallery page shows is in the site, as a PNG.
    figures = re.findall(r"\]\((gallery/[\w.]+\.png)\)", (ROOT / "docs" / "gallery.md").read_text())
    assert len(figures) >= 8
    for name in figures:
        assert (site / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    # The API reference has an entry for every name of the Python API.
    from amigo import pipeline

    reference = (site / "reference" / "pipeline.html").read_text()
    for name in pipeline.__all__:
        assert f'id="amigo.pipeline.{name}"' in reference, name
