"""Traced programs kept on disk (amigo.programs): exact keys, the same results, no
tracing in a second process, and plain filter_jit wherever a program cannot be kept."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo import programs, runtime

#: Python-side calls of the functions below while JAX traces them.
TRACES: list[str] = []


class Pair(NamedTuple):
    total: jax.Array
    scaled: jax.Array


class Weights(eqx.Module):
    values: jax.Array
    table: tuple[float, ...] = eqx.field(static=True)
    power: int = eqx.field(static=True)


@programs.jit
def weighted(weights: Weights, x: jax.Array, offset: float) -> Pair:
    TRACES.append("weighted")
    y = weights.values * x**weights.power + sum(weights.table) + offset
    return Pair(total=jnp.sum(y), scaled=y * 2.0)


@programs.jit
def with_dict(x: jax.Array, options: dict) -> dict:
    TRACES.append("with_dict")
    return {"a": x * options["factor"], "b": (x, None, [x + 1.0])}


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A fresh program folder (the compilation cache is on in the tests: conftest)."""
    monkeypatch.setenv("AMIGO_CACHE_DIR", str(tmp_path))
    programs.release()
    TRACES.clear()
    yield tmp_path / "programs" / programs._source_digest()[:16]
    programs.release()


def _weights(table=(1.0, 2.0), power=2) -> Weights:
    return Weights(jnp.arange(3.0), tuple(table), power)


def test_a_kept_program_gives_filter_jits_results_and_is_written_once(store):
    x = jnp.linspace(0.0, 1.0, 3)
    reference = eqx.filter_jit(weighted.function)(_weights(), x, 0.5)
    out = weighted(_weights(), x, 0.5)
    assert isinstance(out, Pair)
    np.testing.assert_array_equal(out.total, reference.total)
    np.testing.assert_array_equal(out.scaled, reference.scaled)
    assert len(list(store.glob("*.bin"))) == 1
    TRACES.clear()
    programs.release()  # forget it in memory: read from disk, not traced
    again = weighted(_weights(), x + 1.0, 0.5)
    assert TRACES == []
    np.testing.assert_allclose(
        again.total, eqx.filter_jit(weighted.function)(_weights(), x + 1.0, 0.5).total
    )


def test_every_static_value_is_in_the_key(store):
    x = jnp.ones(3)
    weighted(_weights(), x, 0.5)
    weighted(_weights(), x, 0.5)  # same shapes and statics: the same program
    weighted(_weights(), 2.0 * x, 0.5)  # other array values: the same program
    assert len(list(store.glob("*.bin"))) == 1
    weighted(_weights(), x, 0.25)  # a Python float leaf is static
    weighted(_weights(table=(1.0, 2.0 + 1e-15)), x, 0.5)  # a static value, to the last bit
    weighted(_weights(power=3), x, 0.5)  # a static field
    weighted(_weights(), jnp.ones((2, 3)), 0.5)  # a shape
    weighted(_weights(), jnp.ones(3, jnp.int32), 0.5)  # a dtype
    assert len(list(store.glob("*.bin"))) == 6
    np.testing.assert_allclose(
        weighted(_weights(table=(1.0, 3.0)), x, 0.5).total,
        eqx.filter_jit(weighted.function)(_weights(table=(1.0, 3.0)), x, 0.5).total,
    )


def test_only_the_variables_a_trace_reads_are_in_the_key(store, monkeypatch):
    from amigo.model.columns import JVP_BATCH, JVP_BATCH_ENV

    assert programs.TRACED_VARIABLES[JVP_BATCH_ENV] == str(JVP_BATCH)  # the default
    x = jnp.ones(3)
    weighted(_weights(), x, 0.5)
    monkeypatch.setenv("AMIGO_DEBUG", "1")  # a traceback asked for: the same programs
    monkeypatch.setenv("AMIGO_SHARED", "/elsewhere")
    monkeypatch.setenv(JVP_BATCH_ENV, str(JVP_BATCH))  # the default, set: the same
    TRACES.clear()
    programs.release()
    weighted(_weights(), x, 0.5)
    assert TRACES == [] and len(list(store.glob("*.bin"))) == 1
    monkeypatch.setenv(JVP_BATCH_ENV, "64")  # read while tracing: another program
    weighted(_weights(), x, 0.5)
    assert len(list(store.glob("*.bin"))) == 2


def test_plain_containers_come_back_in_their_structure(store):
    out = with_dict(jnp.ones(2), {"factor": 3.0})
    assert set(out) == {"a", "b"}
    assert out["b"][1] is None and isinstance(out["b"][2], list)
    np.testing.assert_array_equal(out["a"], [3.0, 3.0])
    programs.release()
    again = with_dict(jnp.ones(2), {"factor": 3.0})
    assert jax.tree.structure(again) == jax.tree.structure(out)


def test_what_cannot_be_fingerprinted_or_traced_falls_back_to_filter_jit(store):
    # A closure is static under filter_jit but has no exact fingerprint: not kept.
    out = with_dict(jnp.ones(2), {"factor": 2.0, "f": lambda v: v})
    np.testing.assert_array_equal(out["a"], [2.0, 2.0])
    assert not store.exists() or not list(store.glob("*.bin"))
    # Called while tracing, the function is inlined: jit, grad and vmap work through it.
    grad = jax.grad(lambda v: weighted(_weights(), v, 0.5).total)(jnp.ones(3))
    np.testing.assert_allclose(grad, 2.0 * jnp.arange(3.0))
    assert not store.exists() or not list(store.glob("*.bin"))


def test_a_local_function_is_refused():
    with pytest.raises(TypeError, match="module-level"):
        programs.jit(lambda x: x)


def test_off_with_the_compilation_cache(store):
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        weighted(_weights(), jnp.ones(3), 0.5)
        assert not store.parent.exists()
    finally:
        jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])


SCRIPT = textwrap.dedent(
    """
    import sys
    import jax.numpy as jnp
    from amigo import programs

    @programs.jit
    def f(x, n):
        print("traced", file=sys.stderr)
        return jnp.cumsum(x) ** n

    print(f(jnp.arange(4.0), 2).tolist())
    """
)


def test_a_second_process_does_not_trace(tmp_path):
    script = tmp_path / "script.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "AMIGO_CACHE_DIR": str(tmp_path / "cache")}
    env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "xla")
    runs = [
        subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True)
        for _ in range(2)
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
        assert run.stdout.strip() == "[0.0, 1.0, 9.0, 36.0]"
    assert "traced" in runs[0].stderr
    assert "traced" not in runs[1].stderr
    assert len(list(Path(tmp_path / "cache" / "programs").glob("*/*.bin"))) == 1
    # An edit of the function's file is a new program.
    script.write_text(SCRIPT.replace("** n", "** n + 0.0"))
    edited = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True)
    assert "traced" in edited.stderr


def test_fingerprints_are_exact_or_refused():
    def fingerprint(value):
        out: list[str] = []
        programs._static(value, out)
        return out

    a = np.linspace(0.0, 1.0, 2000)  # longer than NumPy prints in full
    b = a.copy()
    b[1000] = np.nextafter(b[1000], 2.0)
    assert fingerprint(a) != fingerprint(b)
    assert fingerprint((1, 2.0)) != fingerprint((1.0, 2))  # types count
    assert fingerprint(0.1) != fingerprint(0.1 + 1e-17 * 10)
    assert fingerprint(np.sum) == [f"named:{np.sum.__module__}:{np.sum.__qualname__}"]
    assert fingerprint(Pair(1, 2)) != fingerprint((1, 2))  # a named tuple's type counts
    # A closure, a JAX array in a static position, an instance of a local class and an
    # object of a compiled type (its state is not visible to Python) have no fingerprint.
    local = object.__new__(type("Local", (), {"x": 1}))
    for refused in (lambda x: x, jnp.ones(2), local, re.compile("a")):
        with pytest.raises(programs._Uncacheable):
            fingerprint(refused)


def test_other_versions_programs_are_pruned_when_stale(store):
    stale, recent = store.parent / ("0" * 16), store.parent / ("1" * 16)
    for folder in (stale, recent):
        folder.mkdir(parents=True)
        (folder / "a.bin").write_bytes(b"x")
    old = 1e9  # 2001
    os.utime(stale, (old, old))
    programs._prune.cache_clear()
    weighted(_weights(), jnp.ones(3), 0.5)
    assert not stale.exists() and recent.exists() and store.exists()


def test_a_damaged_file_is_traced_again(store):
    x = jnp.ones(3)
    expected = weighted(_weights(), x, 0.5).total
    (path,) = store.glob("*.bin")
    whole = path.read_bytes()
    for damage in (whole[:100], whole[:8] + b"\xff" * 200):  # cut short; not text
        path.write_bytes(damage)
        programs.release()
        np.testing.assert_array_equal(weighted(_weights(), x, 0.5).total, expected)
    # Exported again and written whole (about the same size: the serialization's bytes
    # may differ in a few identifiers), and read back.
    assert abs(len(path.read_bytes()) - len(whole)) < 64
    programs.release()
    np.testing.assert_array_equal(weighted(_weights(), x, 0.5).total, expected)


def test_side_by_side_gives_each_calls_result_in_order_in_the_callers_precision(store):
    """Calls in threads: the results of one after the other, in order (finished arrays),
    with the caller's ``jax.enable_x64`` in every thread (a per-thread setting), at most
    ``workers`` at a time; a call's error reaches the caller."""
    import threading

    items = [jnp.linspace(0.0, 1.0, 3) + k for k in range(5)]
    with jax.enable_x64(True):
        wide = [jnp.asarray(np.arange(3.0) + k) for k in range(5)]
        alone = [weighted(_weights(), x, 0.5) for x in wide]
        threads: set[str] = set()
        # The first two calls wait for each other (they must run at once: a pool that ran
        # them one after the other would time out here); the count of calls in flight
        # shows no more than ``workers`` ran together. No timing is assumed: a fast call
        # may otherwise leave its thread idle for the next, and one thread do them all.
        meet = threading.Barrier(2, timeout=60)
        lock = threading.Lock()
        started = [0]
        running = [0, 0]  # now, most

        def call(x):
            with lock:
                started[0] += 1
                first_two = started[0] <= 2
                running[0] += 1
                running[1] = max(running)
            threads.add(threading.current_thread().name)
            if first_two:
                meet.wait()
            assert jax.config.jax_enable_x64
            result = weighted(_weights(), x, 0.5)
            with lock:
                running[0] -= 1
            return result

        together = programs.side_by_side(call, wide, workers=2)
    assert len(threads) == 2 and threading.current_thread().name not in threads
    assert running[1] == 2
    for a, b in zip(together, alone, strict=True):
        assert a.total.dtype == np.float64
        np.testing.assert_array_equal(a.total, b.total)
        np.testing.assert_array_equal(a.scaled, b.scaled)
    narrow = programs.side_by_side(lambda x: weighted(_weights(), x, 0.5), items)
    assert [p.total.dtype for p in narrow] == [np.float32] * 5
    assert programs.side_by_side(lambda x: x + 1, [1]) == [2]  # one item: this thread
    assert programs.side_by_side(lambda x: x, []) == []
    with pytest.raises(ZeroDivisionError):
        programs.side_by_side(lambda x: 1 / x, [1, 0, 2])
    assert runtime.cores() >= 1


def test_threads_that_want_one_program_at_once_read_it_once(store, monkeypatch):
    """Two threads calling a kept program for the first time at once (NUTS's chains)
    deserialize and compile it once, not once each (the loading lock)."""
    x = jnp.linspace(0.0, 1.0, 3)
    weighted(_weights(), x, 0.5)  # written to disk
    programs.release()
    TRACES.clear()
    compiled = []
    caller = programs._caller

    def counting(exported):
        compiled.append(exported)
        return caller(exported)

    monkeypatch.setattr(programs, "_caller", counting)
    out = programs.side_by_side(lambda y: weighted(_weights(), y, 0.5), [x, x + 1.0, x + 2.0])
    assert len(compiled) == 1 and TRACES == []  # read from disk, once
    np.testing.assert_allclose(out[2].total, weighted.jitted(_weights(), x + 2.0, 0.5).total)
