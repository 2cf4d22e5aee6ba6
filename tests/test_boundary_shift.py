"""The physical charge-migration account (amigo.model.detector.boundary) against hand
calculations: one boundary's shift and flow, a brute-force loop over every boundary, charge
conservation, its strength's proportionality, and its place in the ramp and the fit's
options."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.model.detector.boundary import (
    BoundaryShift,
    edge_rates,
    field_coefficients,
)
from amigo.model.detector.ramp import RampModel

pytestmark = pytest.mark.usefixtures("x64")


def _brute_force(charge, edge_x, edge_y, strength, anisotropy, radius, depth):
    """Every boundary by explicit loops, the field of point charges written out."""
    ny, nx = charge.shape
    gain = np.zeros((ny, nx))

    def q(y, x):
        return charge[y, x] if 0 <= y < ny and 0 <= x < nx else 0.0

    def weight(n, m):  # m: pixels beyond the boundary, n: along it
        d = m + 0.5
        return d / (d**2 + n**2 + depth**2) ** 1.5 / (0.5 / (0.25 + depth**2) ** 1.5)

    for y in range(ny):
        for x in range(nx - 1):  # boundary between columns x and x + 1
            field = sum(
                weight(n, m) * (q(y + n, x + 1 + m) - q(y + n, x - m))
                for n in range(-radius, radius + 1)
                for m in range(radius)
            )
            flow = strength * field * edge_x[y, x]
            gain[y, x] += flow
            gain[y, x + 1] -= flow
    for y in range(ny - 1):
        for x in range(nx):  # boundary between rows y and y + 1
            field = sum(
                weight(n, m) * (q(y + 1 + m, x + n) - q(y - m, x + n))
                for n in range(-radius, radius + 1)
                for m in range(radius)
            )
            flow = strength * anisotropy * field * edge_y[y, x]
            gain[y, x] += flow
            gain[y + 1, x] -= flow
    return gain


def test_one_boundary_moves_into_the_brighter_pixel():
    """Charge Q in one pixel only: the boundary to its left neighbour moves into it by
    strength * Q (c[0, 0] = 1), and the neighbour gains that times the photon rate per
    pixel width at the boundary; what it gains the bright pixel loses."""
    charge = np.zeros((1, 2))
    charge[0, 1] = 1.0e4
    sub = np.full((1, 2, 3, 3), 5.0)  # 15 e- per strip: 45 e- per pixel width
    edge_x, edge_y = edge_rates(jnp.asarray(sub))
    assert np.allclose(edge_x, 45.0) and edge_y.shape == (0, 2)
    shift = BoundaryShift.create(2.0e-6, radius_pix=1, depth_pix=0.0)
    moved = np.asarray(shift.moved(jnp.asarray(charge), edge_x, edge_y))
    assert moved[0, 0] == pytest.approx(2.0e-6 * 1.0e4 * 45.0)
    assert moved[0, 1] == pytest.approx(-moved[0, 0])


def test_every_boundary_against_a_brute_force_loop():
    rng = np.random.default_rng(3)
    charge = rng.uniform(0.0, 3.0e4, (7, 9))
    sub = rng.uniform(0.0, 50.0, (7, 9, 3, 3))
    edge_x, edge_y = edge_rates(jnp.asarray(sub))
    # The edge rates by hand: mean of the touching strips, per pixel width.
    assert np.allclose(edge_x[2, 4], 1.5 * (sub[2, 4, :, 2].sum() + sub[2, 5, :, 0].sum()))
    assert np.allclose(edge_y[2, 4], 1.5 * (sub[2, 4, 2, :].sum() + sub[3, 4, 0, :].sum()))
    shift = BoundaryShift.create(1.3e-6, anisotropy=0.8, radius_pix=2, depth_pix=0.5)
    moved = np.asarray(shift.moved(jnp.asarray(charge), edge_x, edge_y))
    expected = _brute_force(charge, np.asarray(edge_x), np.asarray(edge_y), 1.3e-6, 0.8, 2, 0.5)
    assert np.allclose(moved, expected, rtol=1e-12, atol=1e-9)
    assert abs(moved.sum()) < 1e-9 * np.abs(moved).sum()  # conserved


def test_coefficients_are_the_normal_field_of_a_point_charge():
    c = field_coefficients(3, 0.5)
    assert c.shape == (7, 3) and c[3, 0] == 1.0
    # Two pixels beyond, one along, against the formula written once more.
    assert c[4, 2] == pytest.approx((2.5 / (2.5**2 + 1 + 0.25) ** 1.5) / (0.5 / 0.5**1.5))
    assert np.allclose(c, c[::-1])  # symmetric along the boundary


def test_the_ramp_with_the_physical_account():
    """Zero strength is the linear ramp exactly; the charge moved is proportional to
    the strength to first order, conserved, and leaves the bright core for its edges."""
    y, x = np.mgrid[0:60, 0:60] / 3.0
    image = 4.0e4 * np.exp(-((x - 10.2) ** 2 + (y - 9.8) ** 2) / 2.0)
    illuminance = jnp.asarray(image / 9.0)
    linear = RampModel.create(shape=(20, 20), linear=True)
    base = linear(illuminance, 4)
    zero = RampModel(BoundaryShift.create(0.0), linear.flat, linear.intra_pixel)
    assert np.allclose(zero(illuminance, 4), base, rtol=0, atol=1e-9)

    def moved(strength):
        ramp = RampModel(BoundaryShift.create(strength), linear.flat, linear.intra_pixel)
        return np.asarray(ramp(illuminance, 4) - base)[-1]

    one, two = moved(1.0e-6), moved(2.0e-6)
    assert abs(one.sum()) < 1e-6 * np.abs(one).sum()
    peak = np.unravel_index(np.argmax(np.asarray(base)[-1]), (20, 20))
    assert one[peak] < 0  # the brightest pixel loses charge: brighter-fatter
    assert np.allclose(two, 2.0 * one, rtol=0.02, atol=0.02 * np.abs(one).max())


def test_a_base_model_with_the_physical_account_saves_and_loads(tmp_path):
    from amigo.model.base import BaseModel, BaseModelConfig, load_base_model, save_base_model

    config = BaseModelConfig(filters=("F480M",), n_wavelengths=3, pupil_npix=64)
    shift = BoundaryShift.create(2.5e-6, anisotropy=0.9, radius_pix=2, depth_pix=0.25)
    base = BaseModel.create(config).with_network(shift)
    loaded = load_base_model(save_base_model(base, tmp_path / "boundary.npz"))
    assert isinstance(loaded.ramp.network, BoundaryShift)
    assert (loaded.ramp.network.radius_pix, loaded.ramp.network.depth_pix) == (2, 0.25)
    assert float(loaded.ramp.network.strength) == pytest.approx(2.5)
    assert float(loaded.ramp.network.anisotropy) == pytest.approx(0.9)


def test_the_base_model_scales_and_names_the_physical_account():
    from amigo.model.base import BaseModel, BaseModelConfig

    config = BaseModelConfig(filters=("F480M",), n_wavelengths=3, pupil_npix=64)
    base = BaseModel.create(config).with_network(BoundaryShift.create(1.0e-6))
    assert not base.linear
    scaled = base.with_migration_scale(1.5)
    assert float(scaled.ramp.network.strength) == pytest.approx(1.5)
    assert scaled.ramp.network.radius_pix == base.ramp.network.radius_pix
