"""The first group's photons, measured end to end on ramps amigo's simulator did not write.

    python benchmarks/first_group.py [--out DIR] [--ngroups 2] [--nints 400] [--seed 0]
                                     [--filter F480M[,F430M,...]] [--flux E_PER_S]
                                     [--read-noise DN] [--reset-noise DN]
                                     [--companion SEP_MAS,PA_DEG,DMAG[/DMAG/...]]...

A few lines of NumPy here write raw ramps (uncal files) of a point source: Poisson
photo-electrons accumulated read by read, a fixed bias map with a per-integration,
per-pixel reset offset, Gaussian read noise, the ADC's integral non-linearity, integer
counts; the expected image is
amigo's nominal instrument (so the optics are exact and what is measured is the ramp
likelihood). A science star, a calibrator star (four times the integrations) and two
dark exposures are written; ``amigo process`` reduces them; ``amigo fit`` runs twice on
the same files, on the slopes alone and with ``--superbias`` (the darks: the first
group's photons enter); ``amigo detect --no-hmc`` gives each a contrast curve.

The table lists the 3-sigma contrast limit (Absil) at 150, 200, 300 and 400 mas for both
fits, the photon-rule limit ``2.5 log10(sqrt(N_p / 100))`` of each (``N_p`` the photons
the fit says it used: NGROUPS - 1 group times without the first group, NGROUPS with
it), and the rule for all the photons. The photon rule predicts a gain of
``1.25 log10(NGROUPS / (NGROUPS - 1))`` mag (0.38 at two groups). ``--companion``
injects companions into the science star (sky separation, position angle east of north,
delta-mag, one per filter with several filters), for a recovery check: the found
companions are listed against the truth. With several filters every filter gets its own
science and calibrator ramps (the same star brightness) and the limits are the grey
companion's (``combined``).
Nothing is asserted; a run at the defaults takes about 10 minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

GAIN_E_PER_DN = 1.61
#: Raw-ramp header of a NIRISS AMI SUB80 NISRAPID exposure (the keywords amigo reads).
PRIMARY = {
    "TELESCOP": "JWST",
    "INSTRUME": "NIRISS",
    "DETECTOR": "NIS",
    "PUPIL": "NRM",
    "EXP_TYPE": "NIS_AMI",
    "READPATT": "NISRAPID",
    "NFRAMES": 1,
    "GROUPGAP": 0,
    "TFRAME": 0.07544,
    "TGROUP": 0.07544,
    "SUBARRAY": "SUB80",
    "SUBSTRT1": 1045,
    "SUBSTRT2": 1,
    "SUBSIZE1": 80,
    "SUBSIZE2": 80,
    "PROGRAM": "09999",
    "VISIT": "001",
    "DATE-OBS": "2026-01-01",
    "TIME-OBS": "00:00:00.000",
    "DATAMODL": "Level1bModel",
}
ROLL: dict[str, float] = {
    "ROLL_REF": 171.8,
    "V3I_YANG": 0.56126717,
    "VPARITY": -1,
    "PA_APER": 172.36126717,
}
BIAS_DN, BIAS_RMS_DN, RESET_DN, READ_DN, ADC_DN = 12000.0, 300.0, 10.0, 12.0, 2.0


def _image(filter_name: str, position_arcsec, companions, flux_e_s: float) -> np.ndarray:
    """(80, 80) expected photo-electrons per second: the nominal instrument's image of a
    star (and its companions: (sep_mas, pa_deg, dmag) on the sky, placed through the
    nominal detector geometry at the header's PA_APER)."""
    import jax.numpy as jnp

    from amigo.model.detector.linear import sky_to_optical_matrix
    from amigo.model.image import (
        ExposureParams,
        FilterSetup,
        Instrument,
        OpticsParams,
        image_from_log_vis,
    )
    from amigo.orientation import Orientation

    instrument = Instrument.nominal()
    setup = FilterSetup.create(filter_name, instrument)
    optics = OpticsParams.from_instrument(instrument)
    jitter = float(instrument.detector.jitter_arcsec) * 1000.0
    orientation = Orientation(pa_aper_deg=ROLL["PA_APER"], vparity=int(ROLL["VPARITY"]),
                              v3_idl_y_angle_deg=ROLL["V3I_YANG"])  # fmt: skip
    sky_to_optical = sky_to_optical_matrix(orientation, instrument.detector)
    sources = [(np.asarray(position_arcsec), 1.0)]
    for sep_mas, pa_deg, dmag in companions:  # dmag: this filter's
        pa = np.deg2rad(pa_deg)
        east_north = sep_mas / 1000.0 * np.array([np.sin(pa), np.cos(pa)])
        sources.append((np.asarray(position_arcsec) + sky_to_optical @ east_north,
                        10 ** (-0.4 * dmag)))  # fmt: skip
    total = np.zeros((80, 80))
    for position, ratio in sources:
        exposure = ExposureParams(jnp.asarray(position, jnp.float32),
                                  jnp.log(jnp.float32(flux_e_s * ratio)),
                                  jnp.float32(jitter))  # fmt: skip
        total += np.asarray(
            image_from_log_vis(instrument, setup, optics, jnp.asarray(0.0), exposure, None, None)
        )
    return total


def _ramps(
    rng, nints: int, ngroups: int, electrons_per_group: np.ndarray, bias: np.ndarray,
    read_dn: float, reset_dn: float,
):  # fmt: skip
    """(nints, ngroups, 80, 80) raw counts: the first read one group time after the reset."""
    shape = (nints, ngroups, 80, 80)
    light = np.broadcast_to(np.clip(electrons_per_group, 0.0, None), shape)
    charge = np.cumsum(rng.poisson(light), axis=1) / GAIN_E_PER_DN
    reset = reset_dn * rng.standard_normal((nints, 1, 80, 80))
    analog = bias + reset + charge + read_dn * rng.standard_normal(shape)
    # The ADC's integral non-linearity, which `amigo process` corrects (the paper's 2 DN,
    # 1024-count sinusoid): without it the correction would add an error of its own.
    analog = analog + ADC_DN * np.sin(2.0 * np.pi * analog / 1024.0)
    return np.clip(np.rint(analog), 0, 65535).astype(np.uint16)


def _write_uncal(path: Path, raw: np.ndarray, **primary) -> Path:
    from astropy.io import fits

    header = fits.Header()
    for key, value in {**PRIMARY, **primary}.items():
        header[key] = value
    header["NINTS"], header["NGROUPS"] = raw.shape[0], raw.shape[1]
    sci = fits.ImageHDU(raw, name="SCI")
    for key, value in {"BUNIT": "DN", **ROLL}.items():
        sci.header[key] = value
    fits.HDUList([fits.PrimaryHDU(header=header), sci]).writeto(path, overwrite=True)
    return path


def _amigo(*args: str | Path) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "amigo", *map(str, args)], check=True)
    return time.perf_counter() - start


def _limits(detect: Path, filter_name: str) -> dict[str, np.ndarray]:
    """One filter's curve: separations (mas) and 3-sigma delta-mag, Ruffio, Absil (on the
    companion's signal subspace) and Absil on every observable."""
    rows = [r for r in csv.DictReader((detect / "contrast_limits.csv").open())]
    rows = [r for r in rows if r["filter"] == filter_name]
    return {
        key: np.array([float(r[key]) for r in rows])
        for key in ("sep_mas", "ruffio_dmag", "absil_dmag", "absil_all_dmag")
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("first_group_bench"))
    parser.add_argument("--ngroups", type=int, default=2)
    parser.add_argument("--nints", type=int, default=400)
    parser.add_argument("--filter", default="F480M", help="one filter, or several: F380M,F480M")
    parser.add_argument("--flux", type=float, default=2.0e6, help="star, photo-electrons/s")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--read-noise", type=float, default=READ_DN, help="DN per read")
    parser.add_argument("--reset-noise", type=float, default=RESET_DN, help="DN")
    parser.add_argument("--companion", action="append", default=[],
                        help="SEP_MAS,PA_DEG,DMAG (repeatable; DMAG per filter: 8.3/8.0/7.5)")  # fmt: skip
    args = parser.parse_args()
    filters = [f.strip().upper() for f in args.filter.split(",")]
    # SEP,PA,DMAG with one delta-mag, or one per filter separated by "/"
    companions = []
    for text in args.companion:
        sep, pa, dm = text.split(",")
        companions.append((float(sep), float(pa), [float(d) for d in dm.split("/")]))
    out = args.out
    raw, slopes = out / "raw", out / "calslope"
    raw.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    t_g = PRIMARY["TGROUP"]
    bias = BIAS_DN + BIAS_RMS_DN * rng.standard_normal((80, 80))
    start = time.perf_counter()
    files = {}
    plan = []
    for k, filter_name in enumerate(filters):
        dmags = [(sep, pa, dm[k] if len(dm) > 1 else dm[0]) for sep, pa, dm in companions]
        exposure = f"0310{2 + k}"
        sci = _image(filter_name, (0.02, -0.01), dmags, args.flux)
        cal = _image(filter_name, (-0.015, 0.01), [], args.flux)
        plan += [
            (f"sci {filter_name}", "SCI-STAR", "001", exposure, filter_name, args.nints, sci),
            (f"cal {filter_name}", "CAL-STAR", "002", exposure, filter_name, 4 * args.nints, cal),
        ]
    dark = np.zeros((80, 80))
    plan += [("dark1", "DARK", "003", "03102", filters[0], 1000, dark),
             ("dark2", "DARK", "004", "03102", filters[0], 1000, dark)]  # fmt: skip
    for name, target, observation, exposure, filter_name, nints, image in plan:
        counts = _ramps(
            rng, nints, args.ngroups, image * t_g, bias, args.read_noise, args.reset_noise
        )
        files[name] = _write_uncal(
            raw / f"jw09999{observation}001_{exposure}_00001_nis_uncal.fits", counts,
            FILTER=filter_name, TARGPROP=target, TARGNAME=target, OBSERVTN=observation,
            EXPOSURE="00001",
        )  # fmt: skip
    simulated = time.perf_counter() - start
    processed = _amigo("process", *files.values(), "--out", slopes)
    calslope = {
        k: slopes / v.name.replace("_uncal.fits", "_calslope.fits") for k, v in files.items()
    }
    from amigo.model.image import Instrument, save_instrument

    model = out / "nominal.eqx"
    save_instrument(Instrument.nominal(), model)
    rows = {}
    for label, extra in (
        ("slopes", []),
        ("first group", ["--superbias", calslope["dark1"], calslope["dark2"]]),
    ):
        tag = label.replace(" ", "_")
        sci_files = [calslope[f"sci {f}"] for f in filters]
        cal_files = [calslope[f"cal {f}"] for f in filters]
        fit_s = _amigo("fit", "--sci", *sci_files, "--cal", *cal_files, "--model", model,
                       "--out", out / f"fit_{tag}", *extra)  # fmt: skip
        calvis = sorted((out / f"fit_{tag}").glob("*_calvis.fits"))
        detect_s = _amigo("detect", *calvis, "--out", out / f"detect_{tag}", "--no-hmc")
        found = json.loads((out / f"detect_{tag}" / "companions.json").read_text())
        summary = json.loads((out / f"fit_{tag}" / "fit_summary.json").read_text())
        # One filter: its curve; several: the grey companion's (`combined`).
        key = filters[0] if len(filters) == 1 else "combined"
        photon = found["combined"]["photon_limit_dmag"] if len(filters) > 1 else None
        scales = [float(found["sigma_scale"][f]) for f in filters]
        rows[label] = {
            "limits": _limits(out / f"detect_{tag}", key),
            "photon": photon if photon is not None else found["photon_limit_dmag"][key],
            "n_photons": sum(found["photon_count"][f]["n_photons"] for f in filters),
            # the geometric mean over filters (the equal-scale comparison below)
            "sigma_scale": float(np.exp(np.mean(np.log(scales)))),
            "found": [
                {k: c[k] for k in ("sep_mas", "sep_err_mas", "pa_deg", "pa_err_deg", "dmag")}
                for c in found["companions"]
            ],
            "z": [e.get("zscore_std") for e in summary["exposures"]],
            "seconds": (fit_s, detect_s),
        }
    _report(args, rows, companions, simulated, processed)
    (out / "first_group.json").write_text(json.dumps(rows, indent=2, default=_plain) + "\n")


def _plain(x):
    return x.tolist() if isinstance(x, np.ndarray) else str(x)


def _report(args, rows, companions, simulated, processed) -> None:
    seps = (150.0, 200.0, 300.0, 400.0)
    rule_gain = 1.25 * np.log10(args.ngroups / (args.ngroups - 1))
    print(
        f"\n{args.filter}, NGROUPS {args.ngroups}, science {args.nints} integrations "
        f"({args.flux:.3g} e-/s), calibrator {4 * args.nints}; read noise {args.read_noise:g} DN, "
        f"reset noise {args.reset_noise:g} DN; simulated {simulated:.0f} s, "
        f"processed {processed:.0f} s. 3-sigma limits (delta-mag), Ruffio / Absil:"
    )
    header = " ".join(f"{s:>13.0f}" for s in seps)
    print(
        f"{'fit':<12} {'z std':>10} {'N_p':>9} {'rule':>6} {'scale':>5} {header} "
        f"{'fit s':>6} {'det s':>6}"
    )
    for label, row in rows.items():
        curve = row["limits"]
        near = [int(np.argmin(np.abs(curve["sep_mas"] - s))) for s in seps]
        cells = " ".join(
            f"{curve['ruffio_dmag'][i]:>6.2f}/{curve['absil_dmag'][i]:<6.2f}" for i in near
        )
        z = "/".join(f"{v:.2f}" for v in row["z"] if v is not None)
        print(
            f"{label:<12} {z:>10} {row['n_photons']:>9.3g} {row['photon']:>6.2f} "
            f"{row['sigma_scale']:>5.2f} {cells} "
            f"{row['seconds'][0]:>6.0f} {row['seconds'][1]:>6.0f}"
        )
    a, b = rows["slopes"]["limits"], rows["first group"]["limits"]
    band = (a["sep_mas"] >= 150.0) & (a["sep_mas"] <= 400.0)  # same bins in both
    # The limits scale with each fit's sigma_scale (fitted to its DISCOs' scatter): the
    # gain at equal scales is the part the errors themselves explain.
    scales = 2.5 * np.log10(rows["slopes"]["sigma_scale"] / rows["first group"]["sigma_scale"])
    for key in ("ruffio_dmag", "absil_dmag", "absil_all_dmag"):
        gain = float(np.mean(b[key][band] - a[key][band]))
        to_rule = float(np.mean(b[key][band])) - rows["first group"]["photon"]
        print(
            f"{key.removesuffix('_dmag'):>9}, 150-400 mas: first group deeper by {gain:.3f} mag, "
            f"{gain - scales:.3f} at equal sigma_scale (photon rule {rule_gain:.3f}); "
            f"vs the all-photon rule {to_rule:+.3f} mag"
        )
    for label, row in rows.items():
        for c in row["found"]:
            print(f"{label}: found {c}")
    for sep, pa, dm in companions:
        print(f"truth: sep {sep} mas, PA {pa} deg, dmag {'/'.join(map(str, dm))}")


if __name__ == "__main__":
    main()
