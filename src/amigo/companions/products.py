"""Files written by ``amigo detect``: ``companions.json``, ``contrast_limits.csv`` and
``contrast_maps.fits``.

The keys of ``companions.json`` listed in the project's interfaces are a public contract;
amigo adds (never removes) keys: per-companion ``dra_err_mas``, ``ddec_err_mas``,
``per_filter``, ``local_sigma``, ``false_alarm_probability``; top-level
``rejected_candidates`` (above the threshold but inside the inner working angle or with
contrasts no spectrum has), ``sigma_scale_by_kind``, ``photon_count``, ``search``,
``hmc``, ``warnings``, ``sky_convention``. See docs/detect.md.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from amigo._version import __version__
from amigo.companions.limits import COMBINED
from amigo.companions.search import DetectionResult, Estimate
from amigo.io.atomic import atomic_path, write_text

SKY_CONVENTION = (
    "dra_mas positive to the east, ddec_mas to the north; pa_deg east of north "
    "(0..360), from each input's orientation (FITS WCS convention)"
)


def _r(x: float, digits: int = 4) -> float | None:
    x = float(x)
    return round(x, digits) if np.isfinite(x) else None


def _significant(x: float) -> float | None:
    """A probability to three significant figures (null if not finite)."""
    x = float(x)
    return float(f"{x:.3g}") if np.isfinite(x) else None


def _estimate_dict(e: Estimate) -> dict[str, Any]:
    return {
        "sep_mas": _r(e.sep_mas),
        "sep_err_mas": _r(e.sep_err_mas),
        "pa_deg": _r(e.pa_deg),
        "pa_err_deg": _r(e.pa_err_deg),
        "dra_mas": _r(e.dra_mas),
        "ddec_mas": _r(e.ddec_mas),
        "dra_err_mas": _r(e.dra_err_mas),
        "ddec_err_mas": _r(e.ddec_err_mas),
        "dmag": {f: _r(v) for f, v in e.dmag.items()},
        "dmag_err": {f: _r(v) for f, v in e.dmag_err.items()},
    }


def companions_document(result: DetectionResult, inputs: list[str]) -> dict[str, Any]:
    """The content of ``companions.json`` as a plain dictionary."""
    companions = []
    for c in result.companions:
        entry = {
            "id": c.id,
            **_estimate_dict(c.estimate),
            "detection_sigma": _r(c.detection_sigma, 2),
            "method": c.method,
        }
        if c.significance is not None:
            entry["local_sigma"] = _r(c.significance.local_sigma, 2)
            entry["false_alarm_probability"] = _significant(c.significance.false_alarm_probability)
        if c.per_filter:
            entry["per_filter"] = {f: _estimate_dict(e) for f, e in c.per_filter.items()}
        companions.append(entry)
    rejected = [
        {
            **_estimate_dict(r.estimate),
            "reason": r.reason,
            "detection_sigma": _r(r.significance.sigma, 2),
            "local_sigma": _r(r.significance.local_sigma, 2),
            "false_alarm_probability": _significant(r.significance.false_alarm_probability),
            "spectrum_chi2": None if r.spectrum is None else _r(r.spectrum.chi2, 2),
            "spectrum_dof": None if r.spectrum is None else r.spectrum.dof,
            "spectrum_p": None if r.spectrum is None else _significant(r.spectrum.p_value),
            "note": r.note,
        }
        for r in result.rejected
    ]

    def curve_record(curve) -> dict[str, Any]:
        return {
            "sep_mas": [_r(x, 2) for x in curve.sep_mas],
            "sep_lambda_d": [_r(x, 3) for x in curve.sep_lambda_d],
            "dmag_3sigma": [_r(x, 3) for x in curve.ruffio_dmag],
            "dmag_3sigma_std": [_r(x, 3) for x in curve.ruffio_dmag_std],
            "absil_dmag_3sigma": [_r(x, 3) for x in curve.absil_dmag],
            "absil_dmag_3sigma_std": [_r(x, 3) for x in curve.absil_dmag_std],
            "absil_dof": curve.absil_dof,
            "n_obs": curve.n_obs,
            "absil_all_dmag_3sigma": (
                None if curve.absil_all_dmag is None else [_r(x, 3) for x in curve.absil_all_dmag]
            ),
            "method": "ruffio2018",
        }

    # Keyed by filter only (what readers of the contract expect); all filters together
    # (several filters) under their own top-level key.
    limits = {c.filter_name: curve_record(c) for c in result.limits if c.filter_name != COMBINED}
    combined = None
    for curve in result.limits:
        if curve.filter_name == COMBINED:
            rule = curve.photon_limit_dmag
            combined = {
                "contrast_limits": curve_record(curve),
                "photon_limit_dmag": None if rule is None else _r(rule, 3),
                "assumes": "the same flux ratio in every filter",
            }
    document: dict[str, Any] = {
        "amigo_version": __version__,
        "inputs": [os.path.basename(p) for p in inputs],
        "filters": list(result.dataset.filters),
        "companions": companions,
        "rejected_candidates": rejected,
        "sigma_scale": {f: _r(v) for f, v in result.sigma_scale.items()},
        "sigma_scale_by_kind": {
            f: {k: _r(v) for k, v in d.items()} for f, d in result.sigma_scale_by_kind.items()
        },
        "contrast_limits": limits,
        "photon_limit_dmag": {f: _r(v, 3) for f, v in result.photon_limit_dmag.items()},
        "combined": combined,
        "photon_count": {
            f: {
                "n_photons": float(n),
                "source": sorted(
                    {b.photon_source for b in result.dataset.blocks if b.filter_name == f}
                ),
            }
            for f, n in result.photon_counts.items()
        },
        "search": {
            "rmax_mas": result.grid.rmax_mas,
            "step_mas": _r(result.grid.step_mas),
            "inner_working_angle_mas": _r(result.iwa_mas, 2),
            "threshold_sigma": result.settings.threshold_sigma,
            "threshold_is": "global significance (trials of the grid included)",
            "trials": _r(result.trials, 1),
            "iterations": len(result.detection_maps),
            "max_joint_sigma_per_iteration": [
                _r(float(np.max(m.joint_significance)), 2) for m in result.detection_maps
            ],
            "observables": {
                os.path.basename(b.source): sorted({("amplitude", "phase")[k] for k in b.kinds})
                for b in result.dataset.blocks
            },
        },
        "sky_convention": SKY_CONVENTION,
        "warnings": list(result.warnings),
    }
    if result.posterior is not None:
        post = result.posterior
        document["hmc"] = {
            "num_chains": post.num_chains,
            "num_warmup": post.num_warmup,
            "mass_matrix": post.mass_matrix,
            "num_samples": post.num_samples,
            "r_hat_max": _r(post.r_hat_max),
            "ess_min": _r(post.ess_min, 1),
            "ess_percentiles_min": _r(post.ess_percentiles_min, 1),
            "per_filter": {
                f: {
                    "num_warmup": p.num_warmup,
                    "mass_matrix": p.mass_matrix,
                    "num_samples": p.num_samples,
                    "r_hat_max": _r(p.r_hat_max),
                    "ess_min": _r(p.ess_min, 1),
                    "ess_percentiles_min": _r(p.ess_percentiles_min, 1),
                }
                for f, p in result.per_filter_posteriors.items()
            },
        }
    return document


def write_companions_json(
    path: str | os.PathLike[str],
    result: DetectionResult,
    inputs: list[str],
    extra: dict | None = None,
) -> dict:
    """Write ``companions.json`` atomically (``extra`` keys are added at the top level);
    return the document as a reader of the file gets it (JSON types)."""
    document = companions_document(result, inputs) | dict(extra or {})
    text = json.dumps(document, indent=2) + "\n"
    write_text(path, text)
    return json.loads(text)


#: Columns of ``contrast_limits.csv``.
CSV_COLUMNS = (
    "filter",
    "sep_mas",
    "n_sigma",
    "ruffio_dmag",
    "ruffio_dmag_std",
    "absil_dmag",
    "absil_dmag_std",
    "photon_limit_dmag",
    "sep_lambda_d",
    "absil_all_dmag",
    "absil_dof",
    "n_obs",
)


def write_contrast_csv(path: str | os.PathLike[str], result: DetectionResult) -> Path:
    """Write ``contrast_limits.csv``: one row per filter (then ``combined``, all filters
    for a grey companion, when there are several) and separation bin."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for curve in result.limits:
        photon = "" if curve.photon_limit_dmag is None else f"{curve.photon_limit_dmag:.3f}"
        for i in range(curve.sep_mas.size):
            writer.writerow(
                [
                    curve.filter_name,
                    f"{curve.sep_mas[i]:.2f}",
                    f"{curve.n_sigma:g}",
                    f"{curve.ruffio_dmag[i]:.3f}",
                    f"{curve.ruffio_dmag_std[i]:.3f}",
                    f"{curve.absil_dmag[i]:.3f}",
                    f"{curve.absil_dmag_std[i]:.3f}",
                    photon,
                    f"{curve.sep_lambda_d[i]:.3f}",
                    "" if curve.absil_all_dmag is None else f"{curve.absil_all_dmag[i]:.3f}",
                    "" if curve.absil_dof is None else str(curve.absil_dof),
                    "" if curve.n_obs is None else str(curve.n_obs),
                ]
            )
    write_text(path, buffer.getvalue())
    return Path(path)


def _sky_axes(header, step_mas: float, n_x: int, n_y: int) -> None:
    """A linear WCS of sky offsets: axis 1 dRA (east positive), axis 2 dDec, in mas, the
    star at the central pixel (FITS pixels count from 1)."""
    for axis, (kind, n) in enumerate((("DRA", n_x), ("DDEC", n_y)), start=1):
        header[f"CTYPE{axis}"] = kind
        header[f"CUNIT{axis}"] = "mas"
        header[f"CRPIX{axis}"] = (n + 1) / 2.0
        header[f"CRVAL{axis}"] = 0.0
        header[f"CDELT{axis}"] = step_mas


def write_contrast_maps(path: str | os.PathLike[str], result: DetectionResult) -> Path:
    """Write ``contrast_maps.fits`` atomically: the maps behind ``contrast_limits.csv``
    and ``detection_maps.png``, for curves of another shape than its annuli.

    Image extensions, (n_y, n_x) float32 on the search grid, ``[dDec, dRA]`` (dRA east
    positive, a linear WCS in mas, the star at the centre), NaN inside the inner working
    angle and beyond the search radius:

    * ``SIGNIFICANCE``: the joint Gaussian-equivalent significance of one companion at
      each position, on the data as given (before any companion is subtracted);
    * ``ABSIL_<FILTER>``, ``RUFFIO_<FILTER>``: the 3-sigma limits (delta-mag) of each
      filter, then of ``COMBINED`` (all filters, a grey companion) with two or more,
      on the data with the companions found subtracted; their annulus means are the CSV.
    """
    from astropy.io import fits

    grid = result.grid
    n_y, n_x = grid.shape
    primary = fits.PrimaryHDU()
    primary.header["ORIGIN"] = "amigo"
    primary.header["AMIGOVER"] = __version__
    primary.header["STEPMAS"] = (grid.step_mas, "grid step (mas)")
    primary.header["RMAXMAS"] = (grid.rmax_mas, "search radius (mas)")
    primary.header["NCOMP"] = (len(result.companions), "companions found and subtracted")
    hdus: list[Any] = [primary]
    detection = result.detection_maps[0]
    significance = np.where(detection.valid, detection.joint_significance, np.nan)
    hdus.append(fits.ImageHDU(significance.astype(np.float32), name="SIGNIFICANCE"))
    hdus[-1].header["IWAMAS"] = (detection.iwa_mas, "inner working angle (mas)")
    for curve in result.limits:
        for method, values in (("ABSIL", curve.absil_map_dmag), ("RUFFIO", curve.ruffio_map_dmag)):  # fmt: skip
            hdu = fits.ImageHDU(values.astype(np.float32), name=f"{method}_{curve.filter_name.upper()}")  # fmt: skip
            hdu.header["FILTER"] = curve.filter_name
            hdu.header["NSIGMA"] = (curve.n_sigma, "confidence of the limits (sigma)")
            hdu.header["BUNIT"] = "mag"
            hdus.append(hdu)
    for hdu in hdus[1:]:
        _sky_axes(hdu.header, grid.step_mas, n_x, n_y)
    with atomic_path(path) as tmp:
        fits.HDUList(hdus).writeto(tmp)
    return Path(path)
