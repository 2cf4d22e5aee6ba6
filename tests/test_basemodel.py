"""The base model: structure, parameter count, gradients, file round trip, shipped file."""

from __future__ import annotations

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import convolve2d

from amigo.errors import InputError
from amigo.likelihood.slopes import predict_slopes
from amigo.model.base import (
    BaseModel,
    BaseModelConfig,
    default_model_path,
    load_base_model,
    read_metadata,
    save_base_model,
)
from amigo.model.detector.read import default_ipc_kernel

SMALL = BaseModelConfig(filters=("F430M",), shape=(24, 24), pupil_npix=64, n_wavelengths=3)


def _perturbed(model: BaseModel, seed: int = 1) -> BaseModel:
    """Every array leaf replaced by random values (so a round trip checks every one)."""
    arrays, static = eqx.partition(model, eqx.is_array)
    leaves, treedef = jax.tree.flatten(arrays)
    rng = np.random.default_rng(seed)
    leaves = [jnp.asarray(rng.normal(size=x.shape), x.dtype) for x in leaves]
    return eqx.combine(jax.tree.unflatten(treedef, leaves), static)


def test_parameter_count_of_the_full_model():
    model = BaseModel.create()
    per_filter = 7 * 10 + 1  # Zernikes and defocus
    expected = (
        3 * per_filter
        + 7 * 2  # hole centres
        + 7  # hole sizes
        + 5  # jitter, rotation, anisotropy, skew, scale
        + 8640  # network (tests/test_ramp.py checks the architecture)
        + 80 * 80  # flat
        + 5  # intra-pixel
        + 80 * 80  # dark current per pixel
        + 25  # IPC kernel (fixed)
        + 80 * 80  # non-linearity
    )
    assert model.n_parameters == expected
    assert model.with_linear_detector().n_parameters == expected - 8640
    assert model.with_linear_detector().linear and not model.linear


def test_save_load_round_trip_is_bit_exact(tmp_path):
    model = _perturbed(BaseModel.create(SMALL, jax.random.PRNGKey(3)))
    path = save_base_model(model, tmp_path / "m.npz", {"note": "test", "losses": [1.0, 0.5]})
    loaded = load_base_model(path)
    assert loaded.config == model.config
    for a, b in zip(
        jax.tree.leaves(eqx.filter(model, eqx.is_array)),
        jax.tree.leaves(eqx.filter(loaded, eqx.is_array)),
        strict=True,
    ):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(np.asarray(a), np.asarray(b))
    record = read_metadata(path)
    assert record["note"] == "test" and record["losses"] == [1.0, 0.5]
    assert record["network"] is True and record["dtype"] == "float32"
    # The file is a plain npz: no pickle needed to read it.
    with np.load(path, allow_pickle=False) as data:
        assert json.loads(str(data["__metadata__"]))["format"] == "amigo-base-model"
    linear = save_base_model(model.with_linear_detector(), tmp_path / "lin.npz")
    assert load_base_model(linear).linear


def test_load_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a base-model file"):
        load_base_model(bad)
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(InputError, match="no __metadata__"):
        load_base_model(tmp_path / "other.npz")
    with pytest.raises(InputError, match="no such"):
        load_base_model(tmp_path / "missing.npz")
    # A file whose arrays do not match its config.
    path = save_base_model(BaseModel.create(SMALL), tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays.pop(".read.nonlinearity")
    np.savez(tmp_path / "cut.npz", **arrays)
    with pytest.raises(InputError, match="do not match"):
        load_base_model(tmp_path / "cut.npz")


def test_a_version_1_file_with_one_dark_current_loads_with_it_in_every_pixel(tmp_path):
    path = save_base_model(BaseModel.create(SMALL), tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    record = json.loads(str(arrays["__metadata__"]))
    arrays["__metadata__"] = np.asarray(json.dumps({**record, "format_version": 1}))
    arrays[".read.dark_e_per_group"] = np.asarray(0.45, np.float32)
    np.savez(tmp_path / "v1.npz", **arrays)
    dark = np.asarray(load_base_model(tmp_path / "v1.npz").read.dark_e_per_group)
    assert dark.shape == SMALL.shape and np.all(dark == np.float32(0.45))
    # In a current file, a scalar is a damaged file, not an old one.
    arrays["__metadata__"] = np.asarray(json.dumps(record))
    np.savez(tmp_path / "v2.npz", **arrays)
    with pytest.raises(InputError, match="dark_e_per_group has shape"):
        load_base_model(tmp_path / "v2.npz")


def test_linear_detector_slopes_match_a_direct_calculation():
    """Network off, unit flat, no non-linearity: slopes are the IPC-convolved binned
    illuminance per group over the gain (NumPy/SciPy reference), plus nothing else."""
    model = BaseModel.create(SMALL, linear=True)
    rng = np.random.default_rng(2)
    illuminance = rng.uniform(0, 300, (72, 72))
    slopes = np.asarray(predict_slopes(model, jnp.asarray(illuminance, jnp.float32), 5))
    binned = illuminance.reshape(24, 3, 24, 3).sum(axis=(1, 3))
    expected = convolve2d(binned, default_ipc_kernel(), mode="same") / 5 / model.read.gain_e_per_dn
    assert slopes.shape == (4, 24, 24)
    for k in range(4):
        np.testing.assert_allclose(slopes[k], expected, rtol=2e-4, atol=1e-3)


@pytest.mark.slow
def test_gradients_reach_every_parameter_of_the_base_model():
    model = BaseModel.create(SMALL, jax.random.PRNGKey(5), network_init_scale=1.0)
    model = eqx.tree_at(lambda m: m.ramp.intra_pixel.coefficients, model, jnp.full(5, 0.05))
    model = eqx.tree_at(lambda m: m.read.nonlinearity, model, jnp.full((24, 24), -1e-6))
    cache = model.pupil_cache()
    target = jnp.asarray(np.random.default_rng(0).normal(0, 1, (3, 24, 24)), jnp.float32)

    @eqx.filter_jit
    @eqx.filter_grad
    def grad(m):
        image = m.illuminance("F430M", jnp.array([0.02, -0.01]), cache) * 4e5
        return jnp.sum((m.slopes(image, 4) / 100.0 - target) ** 2)

    g = grad(model)
    flat, _ = jax.tree_util.tree_flatten_with_path(eqx.filter(g, eqx.is_array))
    for path, leaf in flat:
        name = jax.tree_util.keystr(path)
        assert bool(jnp.all(jnp.isfinite(leaf))), name
        assert float(jnp.abs(leaf).max()) > 0, name


def test_shipped_model_loads_and_says_what_it_was_trained_on():
    path = default_model_path()
    if not path.is_file():
        pytest.fail(f"no shipped base model at {path}")
    model = load_base_model()
    assert not model.linear and model.ramp.network.n_parameters == 8640
    assert model.config.filters == ("F380M", "F430M", "F480M")
    record = read_metadata(path)
    assert "simulated" in record["trained_on"].lower()
    for key in (
        "scenario",
        "seed",
        "amigo_version",
        "jax_version",
        "training_seconds",
        "machine",
        "history",
        "dtype",
        "date",
    ):
        assert key in record, key
    assert path.stat().st_size < 2_000_000


def test_with_config_changes_only_how_finely_the_optics_is_computed():
    """Same parameters, finer pupil: the image moves towards a much finer computation
    of the same instrument (the pupil sampling error shrinks), and settings that fix
    parameter shapes are refused."""
    model = _perturbed(BaseModel.create(SMALL, jax.random.PRNGKey(4), linear=True), seed=7)
    model = eqx.tree_at(  # a realistic wavefront and geometry, not random numbers
        lambda m: (
            m.zernikes_nm["F430M"],
            m.defocus_nm["F430M"],
            m.hole_centres_m,
            m.hole_sizes_m,
            m.detector,
        ),
        model,
        (
            jnp.asarray(np.random.default_rng(1).normal(0, 20, (7, 10)), jnp.float32),
            jnp.asarray(25.0),
            BaseModel.create(SMALL).hole_centres_m,
            BaseModel.create(SMALL).hole_sizes_m,
            BaseModel.create(SMALL).detector,
        ),
    )

    def image(m: BaseModel) -> np.ndarray:
        return np.asarray(m.illuminance("F430M", jnp.array([0.01, 0.02]), m.pupil_cache()))

    fine = model.with_config(pupil_npix=512)
    assert fine.config.pupil_npix == 512 and fine.config.shape == SMALL.shape
    for a, b in zip(jax.tree.leaves(model), jax.tree.leaves(fine), strict=True):
        assert a is b  # the parameters themselves are untouched
    reference = image(fine)
    errors = [
        float(np.abs(image(model.with_config(pupil_npix=n)) - reference).max() / reference.max())
        for n in (64, 128, 256)
    ]
    assert errors[0] > errors[1] > errors[2], errors
    assert errors[2] < 1e-3
    with pytest.raises(ValueError, match="shape"):
        model.with_config(shape=(16, 16))
    with pytest.raises(ValueError, match="n_zernike"):
        model.with_config(n_zernike=6)


def test_hole_sizes_set_the_area_of_each_hole():
    """Each drawn hole's transmitted area is the hexagon's, (sqrt(3) / 2) w^2 for flat to
    flat w (analytic), for the nominal 0.80 m and for holes grown or shrunk by 2.5 %; an
    older file (format 3, no sizes) loads with the nominal size in every hole."""
    model = BaseModel.create(SMALL, linear=True)
    cache = model.pupil_cache()
    sizes = jnp.asarray([0.80, 0.78, 0.82, 0.80, 0.80, 0.79, 0.81])
    holes = model.optics("F430M", cache).aperture
    for w in (holes.sizes_m, sizes):
        drawn = eqx.tree_at(lambda h: h.sizes_m, holes, w)
        transmission = np.asarray(drawn.hole_transmissions(cache.grid, supersample=3))
        area = transmission.sum(axis=(1, 2)) * cache.grid.pixel_m**2
        np.testing.assert_allclose(area, np.sqrt(3) / 2 * np.asarray(w) ** 2, rtol=2e-3)
    assert np.all(np.asarray(model.hole_sizes_m) == np.float32(0.80))


def test_a_format_3_file_loads_with_nominal_hole_sizes(tmp_path):
    model = eqx.tree_at(lambda m: m.hole_sizes_m, BaseModel.create(SMALL), jnp.full(7, 0.7))
    path = save_base_model(model, tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = dict(data)
    record = json.loads(str(arrays["__metadata__"]))
    arrays["__metadata__"] = np.asarray(json.dumps({**record, "format_version": 3}))
    del arrays[".hole_sizes_m"]
    np.savez(tmp_path / "v3.npz", **arrays)
    sizes = np.asarray(load_base_model(tmp_path / "v3.npz").hole_sizes_m)
    np.testing.assert_array_equal(sizes, np.full(7, np.float32(0.80)))


def test_shipped_level2_model_is_trained_on_real_calibrators_and_says_which():
    """The real-data model for level-2 images (issue 22, item 3): it stands behind the
    pipeline, and its record names the files, the command and the commit."""
    from amigo.model.base import level2_model_path

    path = level2_model_path()
    if path is None:
        pytest.fail("no shipped level-2 model")
    model = load_base_model(path)
    assert model.config.data_level == "level2" and not model.linear
    assert not np.asarray(model.read.nonlinearity).any()
    assert not np.asarray(model.read.dark_e_per_group).any()
    record = read_metadata(path)
    assert record["trained_on"].startswith("real JWST level-2 calibrators")
    names = [e["name"] for e in record["data"]["calibration"]]
    # The last run solved the dark residual from all 33 calibrator files of obs 17, 18 and
    # 20; the one before it trained the rest on 12 of them (its command is kept).
    assert len(names) == 33 and all(n[:10] in ("jw01093017", "jw01093018", "jw01093020")
                                    for n in names)  # fmt: skip
    assert record["dark_residual"]["reference"] == model.config.dark_reference
    assert model.config.dark_reference == "jwst_niriss_dark_0178.fits"
    # ... with what it left unknown, which fits count as noise (format 6).
    assert model.config.dark_prior_dn == record["dark_residual"]["prior_dn"] == 1.6
    assert model.read.group_offsets_chol_dn.shape == (12, 12, 80, 80)
    assert record["initial_model"]["command"].startswith("amigo train --cal ")
    assert record["initial_model"]["command"].count("_cal.fits") == 12 + 3  # cal + val
    assert all(e["level"] == "level2" for e in record["data"]["calibration"])
    assert record["command"].startswith("amigo train --cal ")
    assert len(record["source_commit"]) == 40


def test_a_superbias_travels_in_the_model_file_and_not_behind_the_pipeline(tmp_path):
    from amigo.model.detector.reset import UNKNOWN_VARIANCE_DN2, Superbias

    rng = np.random.default_rng(3)
    known = rng.random((80, 80)) > 0.1
    superbias = Superbias.where_known(
        12000.0 + 300.0 * rng.standard_normal((80, 80)),
        rng.uniform(0.1, 2.0, (80, 80)),
        known,
        n_files=4,
    )
    plain = BaseModel.create(BaseModelConfig(filters=("F480M",)), linear=True)
    assert plain.superbias is None
    save_base_model(plain.with_superbias(superbias), tmp_path / "m.npz")
    back = load_base_model(tmp_path / "m.npz").superbias
    assert back is not None and back.n_files == 4
    # float32 storage: 1e-3 DN at 12,000 DN; the "unknown" sentinel comes back exact.
    np.testing.assert_allclose(back.level_dn, superbias.level_dn, atol=2e-3)
    np.testing.assert_allclose(back.variance_dn2[known], superbias.variance_dn2[known], rtol=1e-6)
    np.testing.assert_array_equal(back.known, known)
    assert np.all(back.variance_dn2[~known] == UNKNOWN_VARIANCE_DN2)
    # The pipeline subtracted the bias: a level-2 view holds none and cannot take one.
    behind = load_base_model(tmp_path / "m.npz").for_level2()
    assert behind.superbias is None and behind.config.superbias_files == 0
    with pytest.raises(ValueError, match="level-2"):
        behind.with_superbias(superbias)
    # Files without one (all before format 7) load with none.
    assert load_base_model().superbias is None


def test_shipped_models_match_their_checksums_and_a_tampered_copy_is_refused(tmp_path):
    import hashlib
    import shutil

    from amigo.model.base import CHECKSUMS_NAME, verify_checksum

    folder = default_model_path().parent
    sums = folder / CHECKSUMS_NAME
    listed = [line.split()[1] for line in sums.read_text().splitlines() if line.strip()]
    shipped = sorted(p.name for p in folder.glob("*.npz"))
    assert sorted(listed) == shipped  # retrained models must update SHA256SUMS
    for name in shipped:
        verify_checksum(folder / name, sums)
    copy = shutil.copy(default_model_path(), tmp_path / default_model_path().name)
    (tmp_path / CHECKSUMS_NAME).write_text(sums.read_text())
    data = bytearray(Path(copy).read_bytes())
    data[len(data) // 2] ^= 0xFF
    Path(copy).write_bytes(bytes(data))
    assert hashlib.sha256(bytes(data)).hexdigest() not in sums.read_text()
    with pytest.raises(InputError, match="reinstall"):
        verify_checksum(Path(copy), tmp_path / CHECKSUMS_NAME)


def test_strong_types_keep_every_value_and_drop_only_the_weak_flag():
    # A model built from Python numbers holds weakly typed scalars; an optimiser's update
    # returns strongly typed ones, and a compiled step keyed on the flag would compile
    # twice. Training starts from the strongly typed model (amigo.training.trainer).
    from amigo.model.optics.model import strong_types

    model = BaseModel.create(BaseModelConfig(filters=("F430M",), shape=(8, 8)), linear=True)
    before = [x for x in jax.tree.leaves(model) if isinstance(x, jax.Array)]
    assert any(x.weak_type for x in before)  # the test has teeth
    after = [x for x in jax.tree.leaves(strong_types(model)) if isinstance(x, jax.Array)]
    assert not any(x.weak_type for x in after)
    assert len(after) == len(before)
    for a, b in zip(after, before, strict=True):
        assert a.dtype == b.dtype and np.array_equal(np.asarray(a), np.asarray(b))
