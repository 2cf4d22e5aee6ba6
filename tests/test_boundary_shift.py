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

    def bound(shift):  # a smooth guard at one 1/3-pixel strip
        return shift / (1.0 + (3.0 * shift) ** 6) ** (1.0 / 6.0)

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
            flow = bound(strength * field) * edge_x[y, x]
            gain[y, x] += flow
            gain[y, x + 1] -= flow
    for y in range(ny - 1):
        for x in range(nx):  # boundary between rows y and y + 1
            field = sum(
                weight(n, m) * (q(y + 1 + m, x + n) - q(y - m, x + n))
                for n in range(-radius, radius + 1)
                for m in range(radius)
            )
            flow = bound(strength * anisotropy * field) * edge_y[y, x]
            gain[y, x] += flow
            gain[y + 1, x] -= flow
    return gain


def test_one_boundary_moves_into_the_brighter_pixel():
    """Charge Q in one pixel only: the boundary to its left neighbour moves into it by
    strength * Q (c[0, 0] = 1; 0.02 pixel, where the guard at 1/3 pixel changes nothing
    measurable), and the neighbour gains that times the photon rate per pixel width at
    the boundary; what it gains the bright pixel loses."""
    charge = np.zeros((1, 2))
    charge[0, 1] = 1.0e4
    sub = np.full((1, 2, 3, 3), 5.0)  # 15 e- per strip: 45 e- per pixel width
    edge_x, edge_y = edge_rates(jnp.asarray(sub))
    assert np.allclose(edge_x, 45.0) and edge_y.shape == (0, 2)
    shift = BoundaryShift.create(2.0e-6, radius_pix=1, depth_pix=0.0)
    moved = np.asarray(shift.moved(jnp.asarray(charge), edge_x, edge_y))
    assert moved[0, 0] == pytest.approx(2.0e-6 * 1.0e4 * 45.0, rel=1e-7)
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


def test_rows_are_columns_transposed_and_single_precision_stays_single():
    """With anisotropy one, the account of a transposed image is the transpose of the
    account (the rows' convention is the columns'); float32 in, float32 out, and the
    same numbers as float64 to single precision."""
    rng = np.random.default_rng(5)
    charge = rng.uniform(0.0, 3.0e4, (6, 8))
    sub = rng.uniform(0.0, 50.0, (6, 8, 3, 3))
    shift = BoundaryShift.create(1.5e-6, radius_pix=2, depth_pix=0.5)
    ex, ey = edge_rates(jnp.asarray(sub))
    moved = np.asarray(shift.moved(jnp.asarray(charge), ex, ey))
    ex_t, ey_t = edge_rates(jnp.asarray(sub.transpose(1, 0, 3, 2)))
    assert np.allclose(ey_t, ex.T) and np.allclose(ex_t, ey.T)
    moved_t = np.asarray(shift.moved(jnp.asarray(charge.T), ex_t, ey_t))
    assert np.allclose(moved_t, moved.T, rtol=1e-12, atol=1e-9)
    single = shift.moved(
        jnp.asarray(charge, jnp.float32), ex.astype(jnp.float32), ey.astype(jnp.float32)
    )
    assert single.dtype == jnp.float32
    assert np.allclose(single, moved, rtol=1e-4, atol=1e-4 * np.abs(moved).max())


def test_large_shifts_are_bounded_and_bad_shapes_refused():
    """A shift is bounded smoothly at one strip (1/3 pixel), the identity for physical
    ones (0.15 pixel: 0.14 % off); a field radius outside 1..8, a negative or non-finite
    depth are refused."""
    from amigo.model.detector.boundary import MAX_SHIFT_PIX

    charge = np.zeros((1, 2))
    charge[0, 1] = 1.0e4
    edges = edge_rates(jnp.full((1, 2, 3, 3), 5.0))
    strong = BoundaryShift.create(1.5e-5, radius_pix=1, depth_pix=0.0)  # 0.15 pixel
    assert float(strong.moved(jnp.asarray(charge), *edges)[0, 0]) == pytest.approx(
        0.15 * 45.0 * (1 - 0.0014), rel=2e-4
    )
    huge = BoundaryShift.create(1.0e-3, radius_pix=1, depth_pix=0.0)  # 10 pixels
    moved = float(huge.moved(jnp.asarray(charge), *edges)[0, 0])
    assert moved == pytest.approx(MAX_SHIFT_PIX * 45.0, rel=1e-6)
    for radius, depth in ((0, 0.5), (9, 0.5), (2.5, 0.5), (2, -0.1), (2, float("nan"))):
        with pytest.raises(ValueError):
            BoundaryShift.create(1e-6, radius_pix=radius, depth_pix=depth)


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
    # A damaged shape record: one line naming the file, not a traceback later.
    import json

    from amigo.errors import InputError

    with np.load(tmp_path / "boundary.npz") as data:
        arrays = dict(data)
    key = next(k for k in arrays if arrays[k].dtype.kind == "U")
    record = json.loads(str(arrays[key]))
    record["boundary_shift"]["radius_pix"] = 0
    arrays[key] = np.asarray(json.dumps(record))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=r"bad\.npz.*boundary_shift"):
        load_base_model(tmp_path / "bad.npz")


def test_the_fit_options_map_to_the_physical_account(tmp_path):
    """--detector boundary (the default for calslope files) puts the account in the
    network's place and names it; a model file holding the account keeps its own strength
    and shape, named by what it holds."""
    from amigo.fitting.ramp_fit import RampDetector
    from amigo.model.base import BaseModel, BaseModelConfig, save_base_model
    from amigo.pipeline._fit import _fit_model

    config = BaseModelConfig(filters=("F480M",), n_wavelengths=3, pupil_npix=64)
    network = save_base_model(BaseModel.create(config), tmp_path / "net.npz")
    fitted = _fit_model(network, "boundary", "calslope")
    assert fitted.detector == "boundary" and isinstance(fitted.base.ramp.network, BoundaryShift)
    assert RampDetector(fitted.base, {}).mode == "boundary"
    # Raw ramps default to the account (since 2026-12-01); --detector full keeps the network.
    default = _fit_model(network, None, "calslope")
    assert default.detector == "boundary" and isinstance(default.base.ramp.network, BoundaryShift)
    assert float(default.base.ramp.network.strength) == pytest.approx(1.8)
    assert _fit_model(network, "full", "calslope").detector == "full"
    assert _fit_model(network, "linear", "calslope").base.linear
    own = BoundaryShift.create(2.5e-6, radius_pix=2, depth_pix=0.0)
    held = save_base_model(BaseModel.create(config).with_network(own), tmp_path / "own.npz")
    for detector in (None, "boundary"):
        kept = _fit_model(held, detector, "calslope")
        assert kept.detector == "boundary"
        assert float(kept.base.ramp.network.strength) == pytest.approx(2.5)
        assert kept.base.ramp.network.radius_pix == 2
    # Level-2 images cannot measure its strength: --detector full (its ramp) is refused;
    # by default a model of raw ramps fits level-2 images with its linear detector.
    from amigo.errors import InputError

    with pytest.raises(InputError, match=r"own\.npz.*calslope"):
        _fit_model(held, "full", "level2")
    assert _fit_model(held, None, "level2").detector == "linear"


def test_the_base_model_scales_and_names_the_physical_account():
    from amigo.model.base import BaseModel, BaseModelConfig

    config = BaseModelConfig(filters=("F480M",), n_wavelengths=3, pupil_npix=64)
    base = BaseModel.create(config).with_network(BoundaryShift.create(1.0e-6))
    assert not base.linear
    scaled = base.with_migration_scale(1.5)
    assert float(scaled.ramp.network.strength) == pytest.approx(1.5)
    assert scaled.ramp.network.radius_pix == base.ramp.network.radius_pix
