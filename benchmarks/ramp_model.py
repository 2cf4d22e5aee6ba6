"""Time the ramp model (charge-migration network) and read model on one exposure.

Prints a table: forward and gradient (w.r.t. every parameter of the ramp and read models)
time for one integration ramp of N groups on the SUB80 grid, float32 and float64, with the
network and with linear charge accumulation. Run: ``python benchmarks/ramp_model.py``.
"""

from __future__ import annotations

import argparse
import platform
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from amigo.model.detector.ramp import RampModel
from amigo.model.detector.read import ReadModel, slopes


def gaussian_illuminance(peak_e: float, dtype) -> jax.Array:
    y, x = np.mgrid[:240, :240]
    image = peak_e / 9 * np.exp(-((x - 121) ** 2 + (y - 118) ** 2) / (2 * 6.0**2))
    return jnp.asarray(image, dtype)


def best_of(function, repeats: int) -> float:
    function()  # compile
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return min(times)


def run(ngroups: int, linear: bool, dtype, repeats: int) -> tuple[float, float]:
    ramp = RampModel.create(jax.random.PRNGKey(0), linear=linear)
    read = ReadModel.create()
    model = jax.tree.map(lambda a: a.astype(dtype) if eqx.is_inexact_array(a) else a, (ramp, read))
    illuminance = gaussian_illuminance(4.8e4, dtype)
    data = jnp.zeros((ngroups - 1, 80, 80), dtype)

    @eqx.filter_jit
    def forward(m):
        r, e = m
        return slopes(e(r(illuminance, ngroups)))

    @eqx.filter_jit
    def gradient(m):
        return eqx.filter_grad(lambda mm: jnp.sum((forward(mm) - data) ** 2))(m)

    return best_of(lambda: forward(model), repeats), best_of(lambda: gradient(model), repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--ngroups", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"ramp + read model, SUB80, {args.ngroups} groups, device {jax.devices()[0]}")
    print(f"machine: {platform.processor() or platform.machine()}, jax {jax.__version__}")
    print(f"{'detector':<10} {'dtype':<8} {'forward ms':>11} {'gradient ms':>12}")
    for linear in (False, True):
        for dtype in (jnp.float32, jnp.float64):
            with jax.enable_x64(dtype == jnp.float64):
                fwd, grad = run(args.ngroups, linear, dtype, args.repeats)
            name = "linear" if linear else "network"
            print(f"{name:<10} {jnp.dtype(dtype).name:<8} {fwd * 1e3:>11.1f} {grad * 1e3:>12.1f}")


if __name__ == "__main__":
    main()
