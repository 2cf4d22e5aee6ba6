"""The commands themselves on hostile inputs and hostile output folders: exit status 2, one
line naming the file on stderr, no traceback, the input unchanged, nothing partial written
(tests/test_fuzz_inputs.py fuzzes the readers behind them; docs/reliability.md)."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest

from fuzz_cases import Mutation, apply, digest
from test_fuzz_inputs import make_seeds

#: Damage every reader must refuse, whatever the kind of file.
REFUSED = {
    "truncated": Mutation("truncate", 0.5),
    "not FITS": Mutation("truncate", 0.0),
    "NINTS 0": Mutation("keyword", 0, "NINTS", 0),
    "PA_APER text": Mutation("keyword", 1, "PA_APER", "north"),
}


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return make_seeds(tmp_path_factory.mktemp("seeds"))


def run(argv: list, capsys) -> tuple[int, str]:
    from amigo.cli import main

    try:
        main([str(a) for a in argv])
        code = 0
    except SystemExit as exit_:
        code = exit_.code
    return code, capsys.readouterr().err


def check_refused(code: int, stderr: str, name: str) -> None:
    lines = [line for line in stderr.splitlines() if line.startswith("amigo: ")]
    assert code == 2, stderr
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr
    assert any(line.startswith("amigo: error: ") and name in line for line in lines), stderr


def _damaged_copy(seed: Path, mutation: Mutation, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / seed.name
    apply(mutation, seed, path)
    return path


@pytest.mark.parametrize("damage", sorted(REFUSED))
def test_process_refuses_a_damaged_ramp_and_writes_nothing_for_it(damage, seeds, tmp_path, capsys):
    bad = _damaged_copy(seeds["uncal"], REFUSED[damage], tmp_path / "in")
    good = shutil.copy(seeds["uncal"], tmp_path / "in" / "jw9_uncal.fits")
    before = digest(bad)
    out = tmp_path / "out"
    code, stderr = run(["process", bad, good, "--out", out], capsys)
    check_refused(code, stderr, bad.name)
    assert digest(bad) == before
    # The good file is processed; nothing of the bad one, no temporary file.
    assert sorted(p.name for p in out.iterdir()) == ["jw9_calslope.fits"]


@pytest.mark.parametrize("kind", ["cal", "calslope"])
@pytest.mark.parametrize("damage", sorted(REFUSED))
def test_fit_refuses_a_damaged_exposure_before_writing(kind, damage, seeds, tmp_path, capsys):
    mutation = REFUSED[damage]
    if kind == "calslope" and damage == "PA_APER text":
        mutation = Mutation("keyword", 1, "PA_APER", "north")  # the SLOPE header's
    bad = _damaged_copy(seeds[kind], mutation, tmp_path / "sci")
    cal = shutil.copy(seeds[kind], tmp_path / ("cal_" + seeds[kind].name))
    before = digest(bad)
    out = tmp_path / "out"
    code, stderr = run(["fit", "--sci", bad, "--cal", cal, "--out", out], capsys)
    check_refused(code, stderr, bad.name)
    assert digest(bad) == before and not out.exists()


@pytest.mark.parametrize("kind", ["calvis", "oifits"])
@pytest.mark.parametrize("damage", ["truncated", "not FITS"])
def test_detect_refuses_damaged_observables_before_writing(kind, damage, seeds, tmp_path, capsys):
    bad = _damaged_copy(seeds[kind], REFUSED[damage], tmp_path / "in")
    out = tmp_path / "out"
    code, stderr = run(["detect", bad, "--out", out], capsys)
    check_refused(code, stderr, bad.name)
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("kind", ["uncal", "cal", "calslope", "calvis", "oifits"])
def test_info_names_a_fifo_instead_of_waiting_for_it(kind, seeds, tmp_path, capsys):
    fifo = tmp_path / seeds[kind].name
    os.mkfifo(fifo)
    code, stderr = run(["info", fifo], capsys)
    check_refused(code, stderr, fifo.name)
    assert "FIFO" in stderr


@pytest.mark.parametrize("code_name", ["ENOSPC", "EROFS", "EDQUOT"])
def test_a_full_or_read_only_disk_is_one_line_and_leaves_nothing(
    code_name, seeds, tmp_path, capsys, monkeypatch
):
    """The OS error is injected where the product is renamed into place (every product
    goes through amigo.io.atomic); the previous product, if any, stays."""
    import amigo.io.atomic as atomic

    out = tmp_path / "out"
    out.mkdir()
    previous = out / "jw1_calslope.fits"
    previous.write_bytes(b"the previous product")

    def refuse(src, dst):
        raise OSError(getattr(errno, code_name), os.strerror(getattr(errno, code_name)))

    monkeypatch.setattr(atomic.os, "replace", refuse)
    code, stderr = run(["process", seeds["uncal"], "--out", out], capsys)
    check_refused(code, stderr, "jw1_calslope.fits")
    assert os.strerror(getattr(errno, code_name)) in stderr
    assert sorted(p.name for p in out.iterdir()) == ["jw1_calslope.fits"]
    assert previous.read_bytes() == b"the previous product"


def test_an_output_folder_that_is_a_file_is_one_line(seeds, tmp_path, capsys):
    out = tmp_path / "out"
    out.write_text("a file, not a folder")
    code, stderr = run(["fit", "--sci", seeds["cal"], "--cal", seeds["calints"], "--out", out],
                       capsys)  # fmt: skip
    check_refused(code, stderr, "out")
    assert out.read_text() == "a file, not a folder"


def _without(seed: Path, folder: Path, extension: str | None = None, keyword: str | None = None):
    """A copy of ``seed`` without one extension or one primary keyword."""
    from astropy.io import fits

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / seed.name
    with fits.open(seed) as hdul:
        kept = fits.HDUList([h.copy() for h in hdul if h.name != extension])
        if keyword:
            del kept[0].header[keyword]
        kept.writeto(path)
    return path


@pytest.mark.parametrize(
    ("kind", "extension", "problem"),
    [
        ("calvis", "DISCO_MATRIX", "lacks the DISCO_MATRIX extension"),
        ("calslope", "BADPIX", "BADPIX"),
        ("oifits", "OI_WAVELENGTH", "OI_WAVELENGTH"),
    ],
)
def test_info_validates_products_as_their_readers_do(kind, extension, problem, seeds, tmp_path,
                                                     capsys):  # fmt: skip
    """`amigo info` identifies *and validates* (the interface): a product the fit or the
    search would refuse is not "ok"."""
    bad = _without(seeds[kind], tmp_path / "in", extension=extension)
    code, stderr = run(["info", bad], capsys)
    check_refused(code, stderr, bad.name)
    assert problem in stderr


def test_detect_says_what_is_wrong_with_a_damaged_calvis(seeds, tmp_path, capsys):
    """Not "neither a calvis nor an OIFITS file" for a truncated calvis: the reader's own
    words; and a calvis without its FILTER keyword is refused (filters are searched by
    name)."""
    truncated = _damaged_copy(seeds["calvis"], REFUSED["truncated"], tmp_path / "a")
    code, stderr = run(["detect", truncated, "--out", tmp_path / "o1"], capsys)
    check_refused(code, stderr, truncated.name)
    assert "truncated" in stderr
    nameless = _without(seeds["calvis"], tmp_path / "b", keyword="FILTER")
    code, stderr = run(["detect", nameless, "--out", tmp_path / "o2"], capsys)
    check_refused(code, stderr, nameless.name)
    assert "FILTER" in stderr


def test_detect_refuses_a_copy_under_another_name(seeds, tmp_path, capsys):
    """The same observables twice would double every chi2 gain, whatever the file name."""
    copy = tmp_path / "copy_calvis.fits"
    shutil.copyfile(seeds["calvis"], copy)
    code, stderr = run(["detect", seeds["calvis"], copy, "--out", tmp_path / "o"], capsys)
    check_refused(code, stderr, copy.name)
    assert "given twice" in stderr and not (tmp_path / "o").exists()


def test_fit_names_the_file_of_the_other_level(seeds, tmp_path, capsys):
    out = tmp_path / "o"
    code, stderr = run(["fit", "--sci", seeds["cal"], "--cal", seeds["calslope"], "--out", out],
                       capsys)  # fmt: skip
    check_refused(code, stderr, seeds["calslope"].name)
    assert "one level" in stderr and not out.exists()


@pytest.mark.parametrize(
    ("option", "problem"),
    [
        (["--knots", "4"], "--knots"),
        (["--model", "nope.npz"], "nope.npz"),
        (["--rmax-mas", "0.5"], "--rmax-mas"),
    ],
)
def test_run_checks_its_options_before_processing_raw_ramps(option, problem, seeds, tmp_path,
                                                            capsys):  # fmt: skip
    """Processing takes minutes on real ramps: a usage error is found before it, and no
    calslope file is written."""
    cal = tmp_path / "jw9_uncal.fits"
    shutil.copyfile(seeds["uncal"], cal)
    out = tmp_path / "o"
    code, stderr = run(["run", "--sci", seeds["uncal"], "--cal", cal, "--out", out, *option],
                       capsys)  # fmt: skip
    assert code == 2 and problem in stderr and stderr.count("\n") == 1, stderr
    assert not out.exists() or not any(out.iterdir())


def test_negative_iteration_counts_are_usage_errors(seeds, tmp_path, capsys):
    for option in (["--max-iterations", "-5"], ["--polish", "-1"]):
        args = ["fit", "--sci", seeds["cal"], "--cal", seeds["calints"], "--out", tmp_path / "o"]
        code, stderr = run([*args, *option], capsys)
        assert code == 2 and option[0] in stderr and stderr.count("\n") == 1, stderr


def test_levels_are_levels_whatever_the_kinds(seeds, tmp_path, capsys):
    """A _cal and a _calints file are one level (level-2 images) for run and a manifest's
    check as for fit; a raw ramp and a level-2 image are two, refused in one line."""
    from amigo.io.jwst import data_kind
    from amigo.io.manifest import Target
    from amigo.pipeline._fit import check_one_level
    from amigo.pipeline._manifest import check_target

    check_one_level({p: data_kind(p) for p in (seeds["cal"], seeds["calints"])})
    check_target(tmp_path / "m.toml", Target("t", (seeds["cal"],), (seeds["calints"],)), {})
    code, stderr = run(["run", "--sci", seeds["uncal"], "--cal", seeds["cal"], "--out",
                        tmp_path / "o"], capsys)  # fmt: skip
    check_refused(code, stderr, seeds["cal"].name)
    assert "a level-2 image (cal)" in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
    with pytest.raises(Exception, match="mixes raw ramps"):
        check_target(tmp_path / "m.toml", Target("t", (seeds["uncal"],), (seeds["calslope"],)), {})
