"""Scenario files and sky placement of companions."""

from __future__ import annotations

import numpy as np
import pytest

from amigo.errors import InputError
from amigo.orientation import Orientation, separation_pa
from amigo.simulation.scenarios import builtin_names, load_scenario, parse_scenario
from amigo.simulation.scene import SkyCompanion, Target, detector_scene, dither_offsets

MINIMAL = """
name = "mini"
program = 1
[[targets]]
name = "STAR"
ra_deg = 10.0
dec_deg = -20.0
[[exposures]]
target = "STAR"
filter = "F430M"
observation = 1
ngroups = 3
nints = 2
peak_dn = 1000
"""


def test_builtin_scenarios_follow_the_papers_tables():
    assert builtin_names() == ["cal4481", "com1093", "demo", "go1843"]
    com = load_scenario("com1093")
    table = {
        (e.target.name, e.filter): (e.ngroups, e.nints_full, e.photons_full) for e in com.exposures
    }
    assert table[("AB-DOR", "F480M")] == (5, 69, 92e6)
    assert table[("AB-DOR", "F380M")] == (2, 160, 97e6)
    assert table[("HD-37093", "F430M")] == (9, 78, 104e6)
    (companion,) = com.exposures[0].target.companions
    assert (companion.sep_mas, companion.pa_deg) == (329.0, 169.5)
    assert com.exposures[0].stem(com.program) == "jw01093012001_03102_00001_nis"

    # The demo: COM 1093's F480M pair, with AB Dor C at its sky PA in the WCS convention.
    demo = load_scenario("demo")
    assert {
        (e.target.name, e.filter): (e.ngroups, e.nints_full, e.photons_full) for e in demo.exposures
    } == {k: v for k, v in table.items() if k[1] == "F480M"}
    (companion,) = demo.exposures[0].target.companions
    assert (companion.sep_mas, companion.pa_deg) == (329.0, 280.5)

    cal = load_scenario("cal4481")
    stars = [e for e in cal.exposures if e.role != "flat"]
    assert len(stars) == 15 and len([e for e in cal.exposures if e.role == "flat"]) == 3
    groups = {e.filter: e.ngroups for e in stars}
    assert groups == {"F380M": 11, "F430M": 20, "F480M": 30}
    f480 = [e for e in stars if e.filter == "F480M"]
    assert sum(e.nints_full for e in f480) == 3800
    assert len({e.offset_pix for e in f480}) == 5
    assert [e.exposure for e in f480] == [1, 2, 3, 4, 5]
    assert stars[0].stem(cal.program) == "jw04481001001_01101_00001_nis"

    go = load_scenario("go1843")
    b, c = go.exposures[0].target.companions
    assert (b.sep_mas, b.pa_deg, b.dmag["F480M"]) == (197.1, 102.3, 7.49)
    assert (c.sep_mas, c.pa_deg, c.dmag["F380M"]) == (103.0, -80.7, 9.14)


def test_bad_scenarios_raise_input_errors_naming_the_problem(tmp_path):
    with pytest.raises(InputError, match="not a built-in"):
        load_scenario(tmp_path / "missing.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        parse_scenario("name = ", "x.toml")
    with pytest.raises(InputError, match="unknown key"):
        parse_scenario(MINIMAL + "colour = 'red'\n", "x.toml")
    with pytest.raises(InputError, match="exactly one of photons_full and peak_dn"):
        parse_scenario(MINIMAL.replace("peak_dn = 1000", ""), "x.toml")
    with pytest.raises(InputError, match="not an AMI filter"):
        parse_scenario(MINIMAL.replace("F430M", "F200W"), "x.toml")
    with pytest.raises(InputError, match="unknown \\[detector\\] keys"):
        parse_scenario(MINIMAL + "[detector]\nbfee = false\n", "x.toml")
    scenario = parse_scenario(MINIMAL + "[detector]\nbfe = false\n", "x.toml")
    assert scenario.detector.bfe is False and scenario.detector.ipc is True


def test_companions_are_placed_through_the_orientation():
    orientation = Orientation.from_roll(123.4)
    target = Target(
        "T",
        "T",
        10.0,
        -20.0,
        (SkyCompanion(250.0, 37.0, {"F380M": 2.0}), SkyCompanion(80.0, 290.0, {"F380M": 5.0})),
    )
    scene = detector_scene(target, "F380M", orientation, (40.0, 41.0), 1000.0)
    primary, *companions = scene.sources
    for companion, source in zip(target.companions, companions, strict=True):
        dra, ddec = orientation.detector_to_sky(source.x_pix - 40.0, source.y_pix - 41.0)
        sep, pa = separation_pa(dra, ddec)
        assert sep == pytest.approx(companion.sep_mas)
        assert pa == pytest.approx(companion.pa_deg % 360.0)
        assert source.photons_per_s == pytest.approx(
            1000.0 * 10 ** (-0.4 * companion.dmag["F380M"])
        )
    assert dither_offsets("5-point-subpixel")[1] == (0.5, 0.0)
    assert dither_offsets([[0.1, 0.2]]) == ((0.1, 0.2),)
    with pytest.raises(ValueError, match="unknown dither"):
        dither_offsets("SPIRAL")
    assert np.isfinite(primary.x_pix)
