"""The persistent compilation cache (amigo.cachedir): on by default, where the user says."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from amigo.cachedir import cache_dir, enable_compilation_cache

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _env(tmp_path: Path) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": SRC, "JAX_PLATFORMS": "cpu"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the test session's own cache
    env.pop("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", None)
    env.pop("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", None)  # the command line's default
    env["AMIGO_CACHE_DIR"] = str(tmp_path / "cache")
    return env


def test_an_explicit_jax_setting_wins_and_an_empty_one_turns_the_cache_off(monkeypatch, tmp_path):
    monkeypatch.setenv("AMIGO_CACHE_DIR", str(tmp_path))
    assert cache_dir() == tmp_path
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "mine"))
    assert enable_compilation_cache() == tmp_path / "mine"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "")
    assert enable_compilation_cache() is None
    assert not (tmp_path / "xla").exists() and not (tmp_path / "xla-lines").exists()


def test_a_compiled_program_is_written_to_the_amigo_cache(tmp_path):
    # amigo as a library, JAX imported first: the cache is switched on through JAX's config.
    code = (
        "import jax, jax.numpy as jnp\n"
        "from amigo.cachedir import enable_compilation_cache\n"
        "folder = enable_compilation_cache()\n"
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.0)\n"
        "jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3)).block_until_ready()\n"
        "print(folder)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], env=_env(tmp_path), capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    folder = tmp_path / "cache" / "xla"
    assert run.stdout.strip() == str(folder)
    assert any(folder.iterdir()), "no compiled program was written"


def test_the_command_line_creates_the_cache_folder(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "amigo", "info", "--help"],
        env=_env(tmp_path), capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    # One line per operation in the programs (amigo.runtime): their own folder, since
    # JAX's cache keys a program without its locations.
    assert (tmp_path / "cache" / "xla-lines").is_dir()
    assert not (tmp_path / "cache" / "xla").exists()
    env = {**_env(tmp_path / "full"), "JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS": "true"}
    run = subprocess.run(
        [sys.executable, "-m", "amigo", "info", "--help"], env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "full" / "cache" / "xla").is_dir()
