"""amigo.runtime: the XLA flag that makes the CPU's matrix products reproducible."""

from __future__ import annotations

import os
import subprocess
import sys

from amigo.runtime import EIGEN_THREADS_FLAG, reproducible_cpu


def test_the_flag_is_added_once_and_a_users_choice_wins(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    reproducible_cpu()
    reproducible_cpu()
    flags = os.environ["XLA_FLAGS"].split()
    assert flags == ["--xla_force_host_platform_device_count=2", f"{EIGEN_THREADS_FLAG}=false"]
    monkeypatch.setenv("XLA_FLAGS", f"{EIGEN_THREADS_FLAG}=true")
    reproducible_cpu()
    assert os.environ["XLA_FLAGS"] == f"{EIGEN_THREADS_FLAG}=true"


def test_it_says_whether_jax_will_read_it():
    """Before JAX's first computation the flag applies; after it, JAX has read its flags."""
    code = (
        "from amigo.runtime import reproducible_cpu\n"
        "import jax.numpy as jnp\n"
        "before = reproducible_cpu()\n"
        "float(jnp.ones(3).sum())\n"
        "print(before, reproducible_cpu())\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    assert out.stdout.split() == ["True", "False"]
