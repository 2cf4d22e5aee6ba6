"""The dark residual of level-2 images (amigo.model.detector.dark_residual).

* The offset Jacobian against independent calculations: the ordinary least-squares slope
  of a read offset (analytic) where the pipeline's weights are uniform (faint pixels),
  and stcal's own ramp fit of a ramp with one read offset added (bright pixels too).
* The read model adds the offsets to the group reads it has, none past them.
* The normal equations recover white per-group offsets from exposures of a few NGROUPS
  and predict the pattern at NGROUPS they never saw as well as the prior allows.
* ``solve_dark_residual`` on simulated level-2 calibrators of a small model, behind one
  dark reference file; a model applies its offsets only behind that file.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo.likelihood.slopes import PointSourceParams, SlopeData, point_source_slopes
from amigo.model.base import BaseModel, BaseModelConfig, load_base_model, save_base_model
from amigo.model.detector.dark_residual import (
    OffsetSystem,
    level2_offset_response,
    offset_jacobian,
    offset_variance,
)
from amigo.model.detector.pipeline_slope import MODEL_READ_NOISE_CDS_DN
from amigo.model.detector.read import ReadModel, group_offsets
from amigo.training.exposure import solve_dark_residual
from test_pipeline_slope import _stcal

TGROUP = 0.07544
GAIN = 1.61


def _ols_weights(n: int) -> np.ndarray:
    """d(OLS slope * t_g)/d(read g): (g - mean) / sum (g - mean)^2."""
    g = np.arange(n) - 0.5 * (n - 1)
    return g / np.sum(g**2)


@pytest.mark.parametrize("ngroups", [2, 3, 5, 9, 13])
def test_offset_jacobian_of_a_faint_ramp_is_the_least_squares_slope(ngroups):
    # 0.5 DN per group: S/N far below 5, where the pipeline weights every read alike.
    differences = jnp.full((ngroups - 1, 4, 4), 0.5)
    jac = np.asarray(offset_jacobian(differences, 15, TGROUP, GAIN))
    assert jac.shape == (15, 4, 4)
    np.testing.assert_allclose(jac[:ngroups, 0, 0], _ols_weights(ngroups), atol=1e-6)
    assert not jac[ngroups:].any()  # reads past the ramp's end do not enter it


def test_offset_jacobian_follows_the_groups_the_pipeline_fitted():
    """Where the pipeline's charge-migration step cut a pixel's ramp to its first ``n``
    groups, an offset of a later read does not reach its slope, and the earlier reads act
    as in a ramp of ``n`` groups."""
    ngroups = 9
    differences = jnp.full((ngroups - 1, 2, 3), 0.5)
    used = np.array([[9, 5, 3], [2, 9, 7]])
    jac = np.asarray(offset_jacobian(differences, 12, TGROUP, GAIN, 1, used))
    for (y, x), n in np.ndenumerate(used):
        np.testing.assert_allclose(jac[:n, y, x], _ols_weights(n), atol=1e-6)
        assert not jac[n:, y, x].any()


def test_offset_jacobian_is_stcal_s_response_to_a_read_offset():
    # Pixels from faint to bright (the pipeline's weights change with S/N); one
    # integration of 9 groups. stcal fits the ramp with read g raised by delta and
    # lowered by delta: the central difference of its slope is the Jacobian's row g.
    rates = np.array([[2.0, 40.0, 300.0], [2e3, 1e4, 4e4]])  # DN/s
    n = 9
    differences = np.broadcast_to(rates * TGROUP, (n - 1, *rates.shape)).copy()
    ramp = np.concatenate([np.zeros((1, *rates.shape)), np.cumsum(differences, axis=0)])
    with jax.enable_x64(True):
        jac = np.asarray(offset_jacobian(jnp.asarray(differences), n, TGROUP, GAIN))
    noise = np.full(rates.shape, MODEL_READ_NOISE_CDS_DN)
    gains = np.full(rates.shape, GAIN)
    delta = 2.0
    worst = 0.0
    for g in range(n):
        slopes = []
        for sign in (1, -1):
            bumped = ramp.copy()
            bumped[g] += sign * delta
            rate, _ = _stcal(
                bumped[None], np.zeros((1, *ramp.shape), bool), tgroup=TGROUP, tframe=TGROUP,
                nframes=1, groupgap=0, read_noise=noise, gain=gains,
            )  # fmt: skip
            slopes.append(np.asarray(rate["slope"], np.float64))
        response = (slopes[0] - slopes[1]) / (2 * delta) * TGROUP
        worst = max(worst, float(np.abs(response - jac[g]).max()))
    print(f"largest difference from stcal: {worst:.2e} (DN per group per DN)")
    # stcal computes in float32 (ramps to ~3e4 DN); measured 3.3e-5
    assert worst < 2e-4, worst
    # ... and the bright pixels' weights are not the faint ones': the test has teeth.
    assert abs(jac[0, 1, 2] - jac[0, 0, 0]) > 0.02


def test_read_offsets_enter_the_group_reads_they_cover():
    offsets = jnp.asarray(np.random.default_rng(0).normal(0, 2.0, (4, 3, 3)))
    np.testing.assert_array_equal(group_offsets(offsets, 3), offsets[:3])
    padded = np.asarray(group_offsets(offsets, 6))
    np.testing.assert_array_equal(padded[:4], offsets)
    assert not padded[4:].any()
    read = ReadModel.create((3, 3))
    charge = jnp.full((6, 3, 3), 100.0)
    with_offsets = ReadModel(
        read.dark_e_per_group, read.ipc_kernel, read.nonlinearity, group_offsets_dn=offsets
    )
    np.testing.assert_allclose(with_offsets(charge) - read(charge), padded, atol=1e-5)


def test_normal_equations_recover_white_offsets_and_predict_unseen_ngroups():
    """Exposures at 3, 6, 9 (x8) and 12 groups, as the COM 1093 calibrators, read-noise
    limited; the offsets' pattern at 5 and 13 groups, which no exposure has, is predicted
    as well as the Gaussian conditional allows (computed here from the same Jacobians)."""
    rng = np.random.default_rng(4)
    prior, n_off, shape = 1.6, 12, (40, 40)
    truth = rng.normal(0, prior, (n_off, *shape))
    faint = {n: offset_jacobian(jnp.full((n - 1, *shape), 0.5), n_off, TGROUP, GAIN)
             for n in (3, 5, 6, 9, 12, 13)}  # fmt: skip
    system, again = OffsetSystem.empty(n_off, shape), OffsetSystem.empty(n_off, shape)
    sigma = 0.05  # DN per group: the noise of a 60-integration level-2 halo pixel
    exposures = []
    for n in (3, 6, *[9] * 8, 12):
        j = np.asarray(faint[n])
        residual = np.einsum("gyx,gyx->yx", j, truth) + rng.normal(0, sigma, shape)
        system.add(j, residual, np.full(shape, sigma**-2), n)
        exposures.append((j, residual, n))
    assert system.ngroups == [3, 6, 9, 9, 9, 9, 9, 9, 9, 9, 12]
    solved = system.solve(prior)
    # Residuals taken with the solved offsets in the model, solved from there: a fixed point.
    for j, residual, n in exposures:
        again.add(j, residual - np.einsum("gyx,gyx->yx", j, solved), np.full(shape, sigma**-2), n)
    np.testing.assert_allclose(again.solve(prior, current=solved), solved, atol=1e-8)

    def pattern(offsets, n):
        return np.einsum("gyx,gyx->yx", np.asarray(faint[n]), offsets)

    for n in (9, 12):  # seen: recovered to the noise of the exposures
        error = pattern(solved, n) - pattern(truth, n)
        assert np.std(error) < 2 * sigma, (n, np.std(error))
    # Unseen: the part of the pattern the Gaussian posterior leaves, on average
    # row^T C row / (prior^2 |row|^2), C = (sum_e J_e J_e^T / sigma^2 + I / prior^2)^-1.
    posterior = np.linalg.inv(system.precision[0, 0] + np.eye(n_off) / prior**2)
    for n in (5, 13):
        left = np.var(pattern(truth, n) - pattern(solved, n)) / np.var(pattern(truth, n))
        row = np.asarray(faint[n])[:, 0, 0]
        expected = row @ posterior @ row / (prior**2 * row @ row)
        print(f"{n} groups: {left:.3f} of the pattern left, {expected:.3f} expected")
        assert left < 0.5
        assert left == pytest.approx(expected, rel=0.1)


def test_offset_variance_states_what_the_solve_left_unknown():
    """The variance the fit adds to an image at NGROUPS the calibrators never had (2 and 4,
    as AB Dor's F380M and HD 37093's obs 15 F380M; 20, past the reads solved) is the
    spread of the truth about the solved offsets: prediction errors divided by its square
    root have unit variance. Without a posterior (another dark reference) the prior's."""
    rng = np.random.default_rng(7)
    prior, n_off, shape = 1.6, 12, (60, 60)
    truth = rng.normal(0, prior, (n_off + 8, *shape))  # reads past the 12 solved exist too
    sigma = 0.05
    system = OffsetSystem.empty(n_off, shape)
    for n in (3, 6, 9, 9, 12):
        j = np.asarray(offset_jacobian(jnp.full((n - 1, *shape), 0.5), n_off, TGROUP, GAIN))
        residual = np.einsum("gyx,gyx->yx", j, truth[:n_off]) + rng.normal(0, sigma, shape)
        system.add(j, residual, np.full(shape, sigma**-2), n)
    solved = system.solve(prior)
    chol = system.posterior_cholesky(prior)
    assert chol.shape == (n_off, n_off, *shape)
    for n in (2, 4, 20):
        j = np.asarray(offset_jacobian(jnp.full((n - 1, *shape), 0.5), n, TGROUP, GAIN))
        error = np.einsum("gyx,gyx->yx", j, truth[:n]) - np.einsum(
            "gyx,gyx->yx", j[:n_off], solved[: min(n, n_off)]
        )
        variance = offset_variance(j, prior, chol)
        z = error / np.sqrt(variance)
        print(f"{n} groups: z std {np.std(z):.3f}, sigma {np.sqrt(variance.mean()):.3f} DN")
        assert np.std(z) == pytest.approx(1.0, abs=0.05)
        # Some of it is known: less than the prior alone would say.
        assert variance.mean() < 0.9 * offset_variance(j, prior).mean()
    # The prior alone: the OLS slope's variance of white reads, 12 s^2 / (N (N^2 - 1)).
    j = np.asarray(offset_jacobian(jnp.full((1, 2, 2), 0.5), 2, TGROUP, GAIN))
    np.testing.assert_allclose(offset_variance(j, prior), 2 * prior**2, rtol=1e-5)
    # A level-2 image: the same in (DN/s)^2, from the image's own rate.
    rate = np.full(shape, 0.5 / TGROUP)
    image = offset_variance(level2_offset_response(rate, 4, TGROUP, GAIN), prior, chol) / TGROUP**2
    j = np.asarray(offset_jacobian(jnp.full((3, *shape), 0.5), 4, TGROUP, GAIN))
    np.testing.assert_allclose(image, offset_variance(j, prior, chol) / TGROUP**2, rtol=1e-5)


@pytest.fixture(scope="module")
def small_level2():
    config = BaseModelConfig(filters=("F480M",), shape=(80, 80), n_wavelengths=3, pupil_npix=64)
    return BaseModel.create(config, linear=True).for_level2()


def test_solve_dark_residual_on_simulated_calibrators(small_level2, tmp_path):
    base = small_level2
    cache = base.pupil_cache()
    rng = np.random.default_rng(7)
    n = 6
    truth = base.with_dark_residual(
        jnp.asarray(rng.normal(0, 1.6, (n, 80, 80)), jnp.float32), "dark_A.fits"
    )
    positions = [(0.02, -0.01), (-0.03, 0.02), (0.01, 0.04), (0.0, 0.0), (-0.02, -0.03)]
    datasets, params = [], []
    for i, position in enumerate(positions):
        source = PointSourceParams(jnp.asarray(position), jnp.asarray(3e5))
        shape_only = SlopeData.from_rate_image(
            np.zeros((80, 80)), np.ones((80, 80)), np.ones((80, 80), bool),
            ngroups=n, group_time_s=TGROUP,
        )  # fmt: skip
        rate = np.asarray(point_source_slopes(truth, cache, source, shape_only))[0] / TGROUP
        error = np.sqrt(np.abs(rate) / 200.0 + 0.3**2)  # DN/s
        noisy = rate + error * rng.normal(size=rate.shape)
        reference = "dark_B.fits" if i == 3 else "dark_A.fits"
        datasets.append(SlopeData.from_rate_image(
            noisy, error, np.ones((80, 80), bool), ngroups=n, group_time_s=TGROUP,
            name=f"cal{i}", dark_reference=reference,
        ))  # fmt: skip
        params.append(source)
    held_out, held_params = datasets.pop(), params.pop()  # never in the solve
    solved, record = solve_dark_residual(base, datasets, params, cache, prior_dn=1.6)
    assert record["reference"] == "dark_A.fits" and record["groups"] == n
    assert record["skipped"] == ["cal3"] and record["exposures"] == ["cal0", "cal1", "cal2"]
    assert solved.config.dark_reference == "dark_A.fits"
    assert solved.config.dark_residual_groups == n

    # The held-out exposure's residuals: at the noise with the solved offsets, well above
    # it without them.
    def z_std(model):
        slope = point_source_slopes(model, cache, held_params, held_out)
        z = (held_out.slopes_dn - slope)[0] * np.asarray(held_out.whitening).reshape(80, 80)
        return float(np.std(np.asarray(z)))

    before, after = z_std(base), z_std(solved)
    print(f"held-out z std: {before:.3f} without offsets, {after:.3f} with")
    assert before > 3.0 and after < 1.6
    # Offsets belong to their dark reference file; elsewhere the model has none.
    assert solved.dark_residual_for("dark_A.fits") is solved
    other = solved.dark_residual_for("dark_B.fits")
    assert other.read.group_offsets_dn is None and other.config.dark_residual_groups == 0
    assert other.read.group_offsets_chol_dn is None

    # The uncertainty they leave travels with them: behind their file the posterior's
    # variance (small where three exposures at these groups measured them), behind
    # another the prior's, none where no dark was subtracted.
    assert solved.config.dark_prior_dn == 1.6
    assert solved.read.group_offsets_chol_dn.shape == (n, n, 80, 80)
    rate = np.full((80, 80), 5.0)
    known = solved.dark_offset_terms("dark_A.fits", rate, n, TGROUP)[1]
    unknown = solved.dark_offset_terms("dark_B.fits", rate, n, TGROUP)[1]
    prior = 1.6**2 * 12 / (n * (n**2 - 1)) / TGROUP**2  # OLS slope of white reads
    np.testing.assert_allclose(unknown, prior, rtol=1e-4)
    assert np.median(known) < 0.5 * prior
    assert not solved.dark_offset_terms("", rate, n, TGROUP)[1].any()
    # ... and through the model file (format 6).
    path = save_base_model(solved, tmp_path / "dark.npz")
    again = load_base_model(path)
    np.testing.assert_array_equal(
        again.read.group_offsets_chol_dn, solved.read.group_offsets_chol_dn
    )
    np.testing.assert_allclose(again.dark_offset_terms("dark_A.fits", rate, n, TGROUP)[1], known)
    with pytest.raises(ValueError, match="level-2"):
        BaseModel.create(BaseModelConfig(filters=("F480M",)), linear=True).with_dark_residual(
            jnp.zeros((3, 80, 80)), "x"
        )


def test_a_fit_adds_the_unknown_offsets_to_level2_images_only(small_level2):
    """``RampDetector`` (what ``amigo fit`` puts in front of a level-2 fit) adds the
    model's ``dark_offset_terms`` variance to the ERR of level-2 images behind a subtracted dark,
    at used pixels, and leaves other images as they are."""
    from amigo.fitting.ramp_fit import Level2Input, RampDetector
    from amigo.likelihood.pixels import ImageData

    n = 4
    chol = np.broadcast_to(0.5 * np.eye(n)[:, :, None, None], (n, n, 80, 80))
    model = small_level2.with_dark_residual(
        jnp.zeros((n, 80, 80)), "dark_A.fits", jnp.asarray(chol), prior_dn=1.6
    )
    mask = np.ones((80, 80), bool)
    mask[:5] = False
    image = ImageData(np.full((80, 80), 3.0), np.full((80, 80), 2.0), mask)
    inputs = {
        "behind": Level2Input(image, 5, 1, TGROUP, "dark_A.fits"),
        "other": Level2Input(image, 5, 1, TGROUP, "dark_B.fits"),
        "none": Level2Input(image, 5, 1, TGROUP, ""),
    }
    detector = RampDetector(model, inputs)
    for name in ("behind", "other"):
        added = model.dark_offset_terms(inputs[name].dark_reference, image.data, 5, TGROUP)[1]
        error = detector.inputs[name].data.error
        np.testing.assert_allclose(error[mask], np.sqrt(4.0 + added[mask]))
        np.testing.assert_array_equal(error[~mask], 2.0)
        assert detector.added_sigma_dn_s[name] == pytest.approx(np.median(np.sqrt(added[mask])))
    # A faint image: least-squares weights w = (-2, -1, 0, 1, 2) / 10 on the 5 reads.
    # Behind its own file the posterior (0.5 DN on reads 0-3) and the prior (1.6 DN) on
    # read 4; behind another the prior on all.
    w = np.arange(-2, 3) / 10
    behind = np.sqrt(0.5**2 * np.sum(w[:4] ** 2) + 1.6**2 * w[4] ** 2) / TGROUP
    assert detector.added_sigma_dn_s["behind"] == pytest.approx(behind, rel=1e-4)
    assert detector.added_sigma_dn_s["other"] == pytest.approx(1.6 * np.sqrt(0.1) / TGROUP)
    assert detector.inputs["none"] is inputs["none"] and "none" not in detector.added_sigma_dn_s
    # what amigo fit says of an image behind another dark (one line), and of the others
    from amigo.pipeline._fit import _dark_reference_note

    note = _dark_reference_note(model, inputs["other"])
    assert note is not None and "dark_B.fits" in note and "behind dark_A.fits" in note
    assert _dark_reference_note(model, inputs["behind"]) is None
    assert _dark_reference_note(model, inputs["none"]) is None
    # Ramps the pipeline's charge-migration step cut to their first 3 reads: the slope of
    # reads 0-2 (weights (-1, 0, 1) / 2) carries their offsets, the prior's behind another file.
    cut = Level2Input(image, 5, 1, TGROUP, "dark_B.fits", np.full((80, 80), 3))
    detector = RampDetector(model, {"cut": cut})
    assert detector.added_sigma_dn_s["cut"] == pytest.approx(1.6 * np.sqrt(0.5) / TGROUP)


def test_the_dark_reference_is_the_one_the_pipeline_subtracted(tmp_path):
    """``R_DARK`` names the file only where the dark step ran (``S_DARK`` COMPLETE, or no
    record of the step); an image whose dark step was skipped carries no reference's
    noise, and gets neither offsets nor their variance."""
    from amigo.io.jwst import read_exposure
    from jwst_files import write_level2

    cases = {
        "done": ({"R_DARK": "crds://jwst_niriss_dark_0178.fits", "S_DARK": "COMPLETE"},
                 "jwst_niriss_dark_0178.fits"),
        "unrecorded": ({"R_DARK": "crds://jwst_niriss_dark_0178.fits"},
                       "jwst_niriss_dark_0178.fits"),
        "skipped": ({"R_DARK": "crds://jwst_niriss_dark_0178.fits", "S_DARK": "SKIPPED"}, ""),
        "none": ({}, ""),
    }  # fmt: skip
    for name, (overrides, expected) in cases.items():
        path = write_level2(tmp_path / f"{name}_cal.fits", np.ones((80, 80)), overrides=overrides)
        assert read_exposure(path).meta.dark_reference == expected, name


def test_a_fit_keeps_the_offsets_only_where_the_image_shows_them(small_level2):
    """``RampDetector.check_dark_patterns``: the amplitude of the model's offset pattern
    measured in each level-2 image's halo is 1 where the image has it and 0 where it does
    not (a simulation whose header names the dark file); the second is then fitted
    without the offsets and without their variance."""
    from types import SimpleNamespace

    from amigo.fitting.filter_fit import FitExposure
    from amigo.fitting.ramp_fit import Level2Input, RampDetector
    from amigo.likelihood.pixels import ImageData

    rng = np.random.default_rng(11)
    n = 6
    chol = np.broadcast_to(0.3 * np.eye(n)[:, :, None, None], (n, n, 80, 80))
    model = small_level2.with_dark_residual(
        jnp.asarray(rng.normal(0, 1.6, (n, 80, 80)), jnp.float32), "dark_A.fits",
        jnp.asarray(chol), prior_dn=1.6,
    )  # fmt: skip
    yy, xx = np.indices((80, 80))
    star = 1e4 * np.exp(-((yy - 40.0) ** 2 + (xx - 45.0) ** 2) / 18.0) + 20.0
    error = np.sqrt(star / 50.0 + 1.5**2)
    pattern = model.dark_offset_terms("dark_A.fits", star, n, TGROUP)[0]
    assert 5.0 < np.std(pattern) < 40.0  # DN/s: a 6-group pattern of 1.6 DN reads
    mask = np.ones((80, 80), bool)
    images = {
        "has_it": star + pattern + error * rng.normal(size=star.shape),
        "lacks_it": star + error * rng.normal(size=star.shape),
    }
    inputs = {k: Level2Input(ImageData(v, error, mask), n, 1, TGROUP, "dark_A.fits")
              for k, v in images.items()}  # fmt: skip
    detector = RampDetector(model, inputs)
    assert set(detector.added_sigma_dn_s) == {"has_it", "lacks_it"}
    # The fit's model carries the offsets: its image is star + pattern for both.
    exposures = [FitExposure(k, "calibrator", "T", detector.inputs[k].data) for k in images]
    fit = SimpleNamespace(exposures=exposures, models=lambda params: [star + pattern] * 2)
    assert detector.check_dark_patterns(fit, None) == ["lacks_it"]
    (a1, s1), (a0, s0) = (detector.pattern_amplitudes[k] for k in ("has_it", "lacks_it"))
    print(f"amplitude {a1:.3f} +- {s1:.3f} with the pattern, {a0:.3f} +- {s0:.3f} without")
    assert abs(a1 - 1.0) < 4 * s1 and abs(a0) < 4 * s0 and s1 < 0.05
    assert detector.inputs["lacks_it"].dark_reference == ""
    assert detector.inputs["lacks_it"].data.error is error  # its ERR as read
    assert "lacks_it" not in detector.added_sigma_dn_s and "has_it" in detector.added_sigma_dn_s
    assert detector.inputs["has_it"].dark_reference == "dark_A.fits"
