"""The non-linear ramp model (charge migration network) and the read electronics."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo.model.detector.ramp import (
    ChargeMigrationNetwork,
    IntraPixelResponse,
    RampModel,
    migration_kernels,
    to_subpixels,
    transport,
)
from amigo.model.detector.read import ReadModel, convolve_ipc, default_ipc_kernel, slopes

pytestmark = pytest.mark.usefixtures("x64")

KEY = jax.random.PRNGKey(0)


def test_kernels_conserve_charge_to_float_precision():
    coefficients = 0.3 * jax.random.normal(KEY, (12, 16, 16), dtype=jnp.float64)
    kernels = migration_kernels(coefficients)
    assert kernels.shape == (16, 16, 3, 3, 3, 3)
    np.testing.assert_allclose(kernels.sum(axis=(-2, -1)), 1.0, atol=1e-14)
    assert float(kernels.min()) >= 0.0


def test_zero_coefficients_keep_charge_in_its_pixel():
    kernels = migration_kernels(jnp.zeros((12, 4, 4)))
    np.testing.assert_allclose(kernels[..., 1, 1], 1.0)
    assert float(jnp.abs(kernels).sum()) == pytest.approx(4 * 4 * 9)


def test_zero_charge_gives_zero_migration():
    network = ChargeMigrationNetwork(KEY)
    assert float(jnp.abs(network(jnp.zeros((80, 80)))).max()) == 0.0


def test_network_parameter_count():
    # 16 fixed gradient maps -> 16 -> 16 -> 16 -> 12, 3x3 kernels, no biases:
    # 3 * (16 * 16 * 9) + 16 * 12 * 9 = 8640 (the paper quotes "8150").
    network = ChargeMigrationNetwork(KEY)
    count = sum(x.size for x in jax.tree.leaves(eqx.filter(network, eqx.is_inexact_array)))
    assert count == network.n_parameters == 8640


def _brute_force_transport(sub, shift_y, shift_x):
    """Independent transport: sample each displaced sub-pixel box densely along y and x
    and count the samples falling in each pixel (numpy loops, no overlap formula; the box
    is a product of intervals, so the 2-D fraction is the product of the 1-D ones)."""
    ny, nx = sub.shape[:2]
    out = np.zeros((ny, nx))
    n = 3000
    u = (np.arange(n) + 0.5) / n / 3.0 - 1.0 / 6.0  # sample points across a 1/3 box

    def fractions(centre, size):
        index = np.floor(centre + u + 0.5).astype(int)
        return np.bincount(index[(index >= 0) & (index < size)], minlength=size) / n

    for py in range(ny):
        for px in range(nx):
            for sy in range(3):
                for sx in range(3):
                    fy = fractions(py + (sy - 1) / 3 + shift_y[py, px, sy, sx], ny)
                    fx = fractions(px + (sx - 1) / 3 + shift_x[py, px, sy, sx], nx)
                    out += sub[py, px, sy, sx] * np.outer(fy, fx)
    return out


def test_transport_matches_brute_force_overlaps():
    rng = np.random.default_rng(3)
    ny = nx = 5
    # Only a constant displacement per pixel (coefficient 0 of x and of y): the polynomial
    # value is then the same for all 9 sub-pixels and easy to reproduce independently.
    coefficients = np.zeros((12, ny, nx))
    coefficients[0] = rng.uniform(-0.3, 0.3, (ny, nx))
    coefficients[6] = rng.uniform(-0.3, 0.3, (ny, nx))
    shift_x = 0.5 * np.tanh(coefficients[0] / 0.5)[..., None, None] * np.ones((3, 3))
    shift_y = 0.5 * np.tanh(coefficients[6] / 0.5)[..., None, None] * np.ones((3, 3))
    sub = rng.uniform(0, 1, (ny, nx, 3, 3))
    ours = transport(jnp.asarray(sub), migration_kernels(jnp.asarray(coefficients)))
    reference = _brute_force_transport(sub, shift_y, shift_x)
    np.testing.assert_allclose(ours, reference, atol=2e-3)


def test_axis_order_shift_along_x_moves_charge_to_the_next_column():
    """Guards against the research code's transposition bug: an x-displacement of pixel
    (2, 1) must move its charge to (2, 2), never to (3, 1) or (1, 2)."""
    coefficients = np.zeros((12, 5, 5))
    coefficients[0, 2, 1] = 0.45  # +x shift of pixel row 2, column 1
    sub = np.zeros((5, 5, 3, 3))
    sub[2, 1] = 1.0 / 9.0
    out = np.asarray(transport(jnp.asarray(sub), migration_kernels(jnp.asarray(coefficients))))
    assert out[2, 2] > 0.2 and out[2, 1] < 0.8
    assert out[3, 1] == out[1, 2] == out[1, 1] == 0.0
    assert out.sum() == pytest.approx(1.0)


def test_to_subpixels_axis_order():
    image = np.arange(36.0).reshape(6, 6)
    blocks = np.asarray(to_subpixels(jnp.asarray(image)))
    assert blocks.shape == (2, 2, 3, 3)
    np.testing.assert_array_equal(blocks[0, 1], image[0:3, 3:6])
    np.testing.assert_array_equal(blocks[1, 0], image[3:6, 0:3])


def test_linear_ramp_is_exactly_linear():
    rng = np.random.default_rng(0)
    illuminance = jnp.asarray(rng.uniform(0, 50, (30, 30)))
    flat = jnp.asarray(rng.uniform(0.9, 1.1, (10, 10)))
    model = eqx.tree_at(lambda m: m.flat, RampModel.create(shape=(10, 10), linear=True), flat)
    charge = model(illuminance, ngroups=7)
    binned = np.asarray(illuminance).reshape(10, 3, 10, 3).sum(axis=(1, 3)) * np.asarray(flat)
    expected = binned[None] * (np.arange(1, 8) / 7)[:, None, None]
    np.testing.assert_allclose(charge, expected, rtol=1e-10)


@pytest.mark.parametrize("n_substeps", [1, 2, 3, 4, 8, 20])
def test_read_weights_are_the_not_a_knot_spline_through_the_substeps(n_substeps):
    """The fixed matrix from the sub-steps to the reads equals interpax's C2 (not-a-knot)
    spline, which the model evaluated before, applied to random charge histories (3 knots:
    interpax's special case, a parabola; 4 and 9: the general system)."""
    import interpax

    from amigo.model.detector.ramp import read_weights

    rng = np.random.default_rng(n_substeps)
    states = np.cumsum(rng.uniform(0, 100, (n_substeps + 1, 50)), axis=0)
    times = jnp.linspace(0.0, 1.0, n_substeps + 1)
    spline = jax.jit(interpax.interp1d, static_argnames="method")  # one program, not op by op
    for ngroups in (2, 5, 8):
        expected = spline(
            jnp.arange(1, ngroups + 1) / ngroups, times, jnp.asarray(states), method="cubic2"
        )
        got = read_weights(n_substeps, ngroups) @ states
        np.testing.assert_allclose(got, np.asarray(expected), rtol=1e-5, atol=1e-3)
    # The same spline as SciPy's (which it replaced, for its import time), to rounding.
    from scipy.interpolate import CubicSpline

    for ngroups in (1, 2, 5, 13):
        reads = np.arange(1, ngroups + 1) / ngroups
        knots = np.linspace(0.0, 1.0, n_substeps + 1)
        scipy_weights = CubicSpline(knots, np.eye(n_substeps + 1), axis=0)(reads)
        np.testing.assert_allclose(read_weights(n_substeps, ngroups), scipy_weights, atol=1e-12)
    # The last read is the end of the ramp: the last sub-step's charge exactly.
    np.testing.assert_allclose(
        read_weights(n_substeps, 5)[-1], np.eye(n_substeps + 1)[-1], atol=1e-12
    )


def test_migration_conserves_total_charge_and_moves_it():
    y, x = np.mgrid[:60, :60]
    illuminance = 4e4 * np.exp(-((x - 30) ** 2 + (y - 30) ** 2) / (2 * 4.0**2))
    illuminance = jnp.asarray(illuminance)
    model = RampModel.create(jax.random.PRNGKey(4), shape=(20, 20))
    model = eqx.tree_at(
        lambda m: m.network.layers[-1].weight, model, model.network.layers[-1].weight * 20
    )
    linear = RampModel.create(shape=(20, 20), linear=True)
    charge = model(illuminance, ngroups=5)
    reference = linear(illuminance, ngroups=5)
    assert float(charge[-1].sum()) == pytest.approx(float(illuminance.sum()), rel=1e-9)
    assert float(jnp.abs(charge[-1] - reference[-1]).max()) > 1.0


def test_gradients_reach_every_parameter():
    y, x = np.mgrid[:30, :30]
    illuminance = jnp.asarray(3e4 * np.exp(-((x - 15) ** 2 + (y - 14) ** 2) / 20.0))
    model = RampModel.create(jax.random.PRNGKey(2), shape=(10, 10))
    model = eqx.tree_at(lambda m: m.intra_pixel, model, IntraPixelResponse(jnp.full(5, 0.05)))
    target = jnp.asarray(np.random.default_rng(1).normal(0, 1, (4, 10, 10)))

    @eqx.filter_grad
    def grad(m):
        return jnp.sum((m(illuminance, 4) / 1e3 - target) ** 2)

    g = grad(model)
    for leaf in jax.tree.leaves(eqx.filter(g, eqx.is_inexact_array)):
        assert bool(jnp.all(jnp.isfinite(leaf)))
        assert float(jnp.abs(leaf).max()) > 0
    for layer in g.network.layers:  # every layer, not just the last
        assert float(jnp.abs(layer.weight).max()) > 0


def test_ipc_matches_direct_sum():
    rng = np.random.default_rng(5)
    frame = rng.uniform(0, 100, (9, 11))
    kernel = default_ipc_kernel()
    assert kernel.sum() == pytest.approx(1.0, abs=1e-15)
    direct = np.zeros_like(frame)
    for y in range(9):
        for x in range(11):
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    if 0 <= y + dy < 9 and 0 <= x + dx < 11:
                        direct[y + dy, x + dx] += kernel[dy + 2, dx + 2] * frame[y, x]
    np.testing.assert_allclose(
        convolve_ipc(jnp.asarray(frame), jnp.asarray(kernel)), direct, rtol=1e-12
    )
    # Orientation: a lone charge couples more "down" (-y) than "up" (+y), per the CRDS values.
    delta = np.zeros((5, 5))
    delta[2, 2] = 1.0
    out = np.asarray(convolve_ipc(jnp.asarray(delta), jnp.asarray(kernel)))
    assert out[1, 2] == pytest.approx(5.028e-3) and out[3, 2] == pytest.approx(3.980e-3)


def test_read_model_matches_direct_calculation():
    rng = np.random.default_rng(6)
    ng, ny, nx = 4, 6, 7
    charge = np.cumsum(rng.uniform(0, 5000, (ng, ny, nx)), axis=0)
    nl = rng.uniform(-2e-6, -1e-6, (ny, nx))
    one_over_f = rng.normal(0, 2, (ng, nx, 2))
    model = ReadModel(
        dark_e_per_group=jnp.asarray(0.45),
        ipc_kernel=jnp.asarray(default_ipc_kernel()),
        nonlinearity=jnp.asarray(nl),
        gain_e_per_dn=1.61,
        one_over_f=jnp.asarray(one_over_f),
    )
    out = np.asarray(model(jnp.asarray(charge)))
    kernel = default_ipc_kernel()
    rows = np.linspace(-1, 1, ny)
    for k in range(ng):
        q = charge[k] + 0.45 * (k + 1)
        padded = np.pad(q, 2)
        ipc = sum(
            kernel[dy + 2, dx + 2] * padded[2 - dy : 2 - dy + ny, 2 - dx : 2 - dx + nx]
            for dy in range(-2, 3)
            for dx in range(-2, 3)
        )
        expected = (ipc + nl * ipc**2) / 1.61
        expected = expected + one_over_f[k, :, 0][None] + rows[:, None] * one_over_f[k, :, 1][None]
        np.testing.assert_allclose(out[k], expected, rtol=1e-10)
    assert slopes(jnp.asarray(out)).shape == (ng - 1, ny, nx)
