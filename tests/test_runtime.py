"""amigo.runtime: the XLA flags that make the CPU's matrix products reproducible and its
compilation faster."""

from __future__ import annotations

import os
import subprocess
import sys

import amigo.runtime as runtime
from amigo.runtime import (
    EIGEN_THREADS_FLAG,
    FUSION_EMITTERS_FLAG,
    OPT_LEVEL_FLAG,
    configure_xla,
    reproducible_cpu,
)


def test_the_flag_is_added_once_and_a_users_choice_wins(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    reproducible_cpu()
    reproducible_cpu()
    flags = os.environ["XLA_FLAGS"].split()
    assert flags == ["--xla_force_host_platform_device_count=2", f"{EIGEN_THREADS_FLAG}=false"]
    monkeypatch.setenv("XLA_FLAGS", f"{EIGEN_THREADS_FLAG}=true")
    reproducible_cpu()
    assert os.environ["XLA_FLAGS"] == f"{EIGEN_THREADS_FLAG}=true"


def _child(code: str) -> str:
    """What ``python -c code`` prints, started without XLA_FLAGS (as a user's shell)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    return done.stdout


def test_it_says_whether_jax_will_read_it():
    """Before JAX's first computation the flag applies; after it, JAX has read its flags."""
    code = (
        "from amigo.runtime import reproducible_cpu\n"
        "import jax.numpy as jnp\n"
        "before = reproducible_cpu()\n"
        "float(jnp.ones(3).sum())\n"
        "print(before, reproducible_cpu())\n"
    )
    assert _child(code).split() == ["True", "False"]


def test_the_older_fusion_emitters_only_where_jaxlib_is_known(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    monkeypatch.setattr(runtime, "_jaxlib_minor", lambda: (0, 10))
    monkeypatch.setattr(runtime, "_accelerator_plugin", lambda: False)
    configure_xla()
    configure_xla()
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=2",
        f"{FUSION_EMITTERS_FLAG}=false",
        f"{OPT_LEVEL_FLAG}=1",
        f"{EIGEN_THREADS_FLAG}=false",
    ]
    # With a GPU's (or TPU's) plugin installed the optimisation level stays XLA's: the
    # flag is not the CPU's alone.
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(runtime, "_accelerator_plugin", lambda: True)
    assert runtime.fast_cpu_compile()
    assert os.environ["XLA_FLAGS"].split() == [f"{FUSION_EMITTERS_FLAG}=false"]
    # A user's choice of one flag keeps theirs and does not stop the other.
    monkeypatch.setenv("XLA_FLAGS", f"{FUSION_EMITTERS_FLAG}=true")
    monkeypatch.setattr(runtime, "_accelerator_plugin", lambda: False)
    assert runtime.fast_cpu_compile()
    assert os.environ["XLA_FLAGS"].split() == [
        f"{FUSION_EMITTERS_FLAG}=true",
        f"{OPT_LEVEL_FLAG}=1",
    ]
    # A jaxlib whose XLA was not measured may not know the flag (XLA then stops the
    # process): nothing is added.
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(runtime, "_jaxlib_minor", lambda: (0, 99))
    assert not runtime.fast_cpu_compile()
    assert FUSION_EMITTERS_FLAG not in os.environ["XLA_FLAGS"]
    monkeypatch.setenv("XLA_FLAGS", f"{FUSION_EMITTERS_FLAG}=true")  # a user's choice wins
    assert runtime.fast_cpu_compile()
    assert os.environ["XLA_FLAGS"] == f"{FUSION_EMITTERS_FLAG}=true"


def test_the_installed_jaxlib_accepts_what_amigo_sets():
    """A new process with amigo's flags starts JAX and computes (an unknown flag would
    stop it); with the jaxlib of this environment the older emitters are asked for."""
    code = (
        "from amigo.runtime import configure_xla\n"
        "configure_xla()\n"
        "import os, jax.numpy as jnp\n"
        "print(float(jnp.ones(3).sum()), os.environ['XLA_FLAGS'])\n"
    )
    out = _child(code)
    assert out.split()[0] == "3.0"
    known = runtime._jaxlib_minor() in runtime.FUSION_EMITTERS_JAXLIB
    assert (FUSION_EMITTERS_FLAG in out) == known
    assert (OPT_LEVEL_FLAG in out) == (known and not runtime._accelerator_plugin())


def test_programs_carry_one_line_per_operation_unless_the_user_asks(monkeypatch):
    """Before JAX starts, short_locations asks for one line per operation (XLA's GPU back
    end formats every frame of a traceback when it loads a program); a user's setting
    wins, and a process that imported JAX already keeps JAX's own."""
    code = (
        "import os\n"
        "from amigo.cachedir import full_tracebacks\n"
        "from amigo.runtime import short_locations\n"
        "short_locations()\n"
        "before = full_tracebacks()\n"
        "import jax\n"
        "assert before == jax.config.jax_include_full_tracebacks_in_locations\n"
        "print(os.environ['JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS'], before)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS"}
    for given, expected in ((None, ["false", "False"]), ("true", ["true", "True"])):
        if given is not None:
            env["JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS"] = given
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
        )
        assert done.stdout.split() == expected
    # This process imported JAX: its setting is left alone.
    monkeypatch.delenv("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", raising=False)
    runtime.short_locations()
    assert "JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS" not in os.environ


def test_a_lowered_program_has_no_tracebacks_after_configure_xla():
    """In a new process: a function lowered after amigo's settings has no callsite
    locations (tracebacks) in its text, one lowered with JAX's default has them."""
    code = (
        "import sys\n"
        "if sys.argv[1] == 'amigo':\n"
        "    from amigo.runtime import configure_xla\n"
        "    configure_xla()\n"
        "import jax, jax.numpy as jnp\n"
        "def inner(x):\n"
        "    return jnp.sin(x) * 2\n"
        "def outer(x):\n"
        "    return inner(x) + 1\n"
        "text = jax.jit(outer).lower(jnp.ones(3)).as_text(debug_info=True)\n"
        "print(text.count('callsite('))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS"}
    counts = {}
    for mode in ("amigo", "plain"):
        done = subprocess.run(
            [sys.executable, "-c", code, mode], capture_output=True, text=True, env=env, check=True
        )
        counts[mode] = int(done.stdout.split()[-1])
    assert counts["amigo"] == 0 and counts["plain"] > 0, counts
