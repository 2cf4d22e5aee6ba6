"""Write calibrated visibilities at the 21 mask baselines as an OIFITS2 file (astropy only).

The calibrated log-visibility ``log V_sci - log V_cal`` of amigo's latent model is
evaluated at the 21 baselines of the mask (:func:`amigo.niriss.baselines_m`), giving
squared visibilities ``V2 = exp(2 log|V|)`` and the 35 closure phases
``phi_ij + phi_jk - phi_ik`` (``i < j < k``), with their full covariance (propagated
linearly from the latent covariance) written as correlations in ``OI_CORR``.

Coordinates follow the OIFITS standard: ``UCOORD`` east and ``VCOORD`` north (metres),
obtained from the pupil-frame baselines ``b`` with the sky->uv-frame matrix ``S`` of the
calvis file as ``S^T b`` (so that ``b . (S theta) = (S^T b) . theta``), and
``V = exp(-2 pi i (u dRA + v dDec) / lambda)`` for a point at ``(dRA, dDec)``.
The single spectral channel is the band's throughput-weighted mean wavelength.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from astropy.io import fits

from amigo import niriss
from amigo._version import __version__
from amigo.io.atomic import atomic_path


def closure_triangles(n_holes: int = niriss.N_HOLES) -> list[tuple[int, int, int]]:
    """The 35 hole triples ``i < j < k``."""
    return list(itertools.combinations(range(n_holes), 3))


def closure_matrix() -> np.ndarray:
    """(35, 21) matrix ``T``: baseline phases -> closure phases ``phi_ij + phi_jk - phi_ik``."""
    pairs = {p: n for n, p in enumerate(niriss.baseline_pairs())}
    triangles = closure_triangles()
    t = np.zeros((len(triangles), len(pairs)))
    for row, (i, j, k) in enumerate(triangles):
        t[row, pairs[(i, j)]] += 1
        t[row, pairs[(j, k)]] += 1
        t[row, pairs[(i, k)]] -= 1
    return t


def _covariance_to_corr(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper-triangle correlations (1-based indices) of a covariance matrix."""
    sigma = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sigma, sigma)
    i, j = np.triu_indices(len(cov), k=1)
    return i + 1, j + 1, corr[i, j]


def creation_date() -> str:
    """The file's creation date for the OIFITS ``DATE`` keyword, ``YYYY-MM-DD`` (UTC).

    Today, unless ``SOURCE_DATE_EPOCH`` (the reproducible-builds convention: seconds since
    1970-01-01 UTC) fixes it: then two runs on different days, or a run resumed after
    midnight, write the same bytes.
    """
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    moment = _dt.datetime.now(_dt.UTC)
    if epoch:
        try:
            moment = _dt.datetime.fromtimestamp(int(epoch), _dt.UTC)
        except (ValueError, OverflowError, OSError):
            pass  # not a number of seconds: the convention says to ignore it
    return moment.strftime("%Y-%m-%d")


def write_oifits(
    path: str | os.PathLike[str],
    *,
    target: str,
    filter_name: str,
    wavelength_m: float,
    bandwidth_m: float,
    log_amp: np.ndarray,
    phase_rad: np.ndarray,
    covariance: np.ndarray,
    sky_to_uv: np.ndarray,
    date_obs: str = "",
    mjd: float = 0.0,
    int_time_s: float = 0.0,
    science_files: Sequence[str] = (),
    n_photons: float | None = None,
) -> Path:
    """Write calibrated visibilities of one target and filter.

    Parameters
    ----------
    science_files
        The science exposures' file names, written as ``NSCI`` and ``SCI_1``... in the
        primary header as in a calvis file: ``amigo detect`` refuses two inputs made from
        the same exposure (its information would count twice).
    n_photons
        The photons behind the science observables, written as ``NPHOT`` as in a calvis
        file (``amigo detect``'s photon rule reads it; without it the rule estimates them
        from the closure phases' errors).
    log_amp, phase_rad
        (21,) calibrated ``log|V|`` and ``arg V`` at :func:`amigo.niriss.baselines_m`.
    covariance
        (42, 42) covariance of ``[log_amp, phase_rad]``.
    sky_to_uv
        (2, 2) sky (mas) -> pupil-frame (mas) matrix (as in the calvis file).
    """
    baselines = niriss.baselines_m()
    pairs = np.array(niriss.baseline_pairs())
    n_b = len(baselines)
    uv_sky = baselines @ np.asarray(sky_to_uv)  # rows: (S^T b)^T
    v2 = np.exp(2.0 * np.asarray(log_amp))
    closure = closure_matrix()
    cp_rad = closure @ np.asarray(phase_rad)
    # Linear propagation: d V2 = 2 V2 d logA;  d CP = T d phi.
    jac = np.zeros((n_b + len(closure), 2 * n_b))
    jac[:n_b, :n_b] = np.diag(2.0 * v2)
    jac[n_b:, n_b:] = closure
    cov = jac @ np.asarray(covariance) @ jac.T
    scale = np.concatenate([np.ones(n_b), np.full(len(closure), np.rad2deg(1.0))])
    cov = cov * np.outer(scale, scale)
    err = np.sqrt(np.diag(cov))
    v2_err, cp_err_deg = err[:n_b], err[n_b:]
    cp_deg = np.rad2deg(cp_rad)

    date = (date_obs.split("T")[0].split(" ")[0] if date_obs else "") or "2000-01-01"
    insname = f"NIRISS_AMI_{filter_name}"
    arrname = "JWST_NRM"
    target_name = target.strip() or "UNKNOWN"

    primary = fits.PrimaryHDU()
    h = primary.header
    h["CONTENT"] = "OIFITS2"
    h["ORIGIN"] = "amigo"
    h["DATE"] = creation_date()
    h["DATE-OBS"] = date
    h["TELESCOP"] = "JWST"
    h["INSTRUME"] = "NIRISS"
    h["INSMODE"] = f"AMI {filter_name}"
    h["OBSTECH"] = "SPARSE_APERTURE_MASKING"
    h["OBSERVER"] = "JWST"
    h["OBJECT"] = target_name
    h["FILTER"] = filter_name
    h["PROCSOFT"] = f"amigo {__version__}"
    h["REFERENC"] = "AMIGO calibrated latent visibilities at the mask baselines"
    if n_photons is not None and np.isfinite(n_photons):
        h["NPHOT"] = (float(n_photons), "photons used for the science observables")
    h["NSCI"] = (len(science_files), "number of science input files")
    for number, name in enumerate(science_files, start=1):
        h[f"SCI_{number}"] = os.path.basename(str(name))

    def table(columns, name, extra):
        hdu = fits.BinTableHDU.from_columns(columns, name=name)
        hdu.header["OI_REVN"] = 2
        for key, value in extra.items():
            hdu.header[key] = value
        return hdu

    target_hdu = table(
        [
            fits.Column("TARGET_ID", "I", array=[1]),
            fits.Column("TARGET", "16A", array=[target_name[:16].ljust(16)]),
            fits.Column("RAEP0", "D", unit="deg", array=[0.0]),
            fits.Column("DECEP0", "D", unit="deg", array=[0.0]),
            fits.Column("EQUINOX", "E", unit="yr", array=[2000.0]),
            fits.Column("RA_ERR", "D", unit="deg", array=[0.0]),
            fits.Column("DEC_ERR", "D", unit="deg", array=[0.0]),
            fits.Column("SYSVEL", "D", unit="m/s", array=[0.0]),
            fits.Column("VELTYP", "8A", array=["UNKNOWN"]),
            fits.Column("VELDEF", "8A", array=["OPTICAL"]),
            fits.Column("PMRA", "D", unit="deg/yr", array=[0.0]),
            fits.Column("PMDEC", "D", unit="deg/yr", array=[0.0]),
            fits.Column("PMRA_ERR", "D", unit="deg/yr", array=[0.0]),
            fits.Column("PMDEC_ERR", "D", unit="deg/yr", array=[0.0]),
            fits.Column("PARALLAX", "E", unit="deg", array=[0.0]),
            fits.Column("PARA_ERR", "E", unit="deg", array=[0.0]),
            fits.Column("SPECTYP", "16A", array=["UNKNOWN"]),
            fits.Column("CATEGORY", "3A", array=["SCI"]),
        ],
        "OI_TARGET",
        {},
    )
    holes = np.asarray(niriss.HOLE_CENTRES_M)
    array_hdu = table(
        [
            fits.Column("TEL_NAME", "16A", array=[f"H{k}" for k in range(len(holes))]),
            fits.Column("STA_NAME", "16A", array=[f"H{k}" for k in range(len(holes))]),
            fits.Column("STA_INDEX", "I", array=np.arange(1, len(holes) + 1)),
            fits.Column("DIAMETER", "E", unit="m", array=np.full(len(holes), 0.8)),
            fits.Column(
                "STAXYZ", "3D", unit="m", array=np.column_stack([holes, np.zeros(len(holes))])
            ),
            fits.Column("FOV", "D", unit="arcsec", array=np.full(len(holes), 2.6)),
            fits.Column("FOVTYPE", "6A", array=["RADIUS"] * len(holes)),
        ],
        "OI_ARRAY",
        {"ARRNAME": arrname, "FRAME": "SKY", "ARRAYX": 0.0, "ARRAYY": 0.0, "ARRAYZ": 0.0},
    )
    wave_hdu = table(
        [
            fits.Column("EFF_WAVE", "E", unit="m", array=[wavelength_m]),
            fits.Column("EFF_BAND", "E", unit="m", array=[bandwidth_m]),
        ],
        "OI_WAVELENGTH",
        {"INSNAME": insname},
    )
    i, j, c = _covariance_to_corr(cov)
    corr_hdu = table(
        [
            fits.Column("IINDX", "J", array=i),
            fits.Column("JINDX", "J", array=j),
            fits.Column("CORR", "D", array=c),
        ],
        "OI_CORR",
        {"CORRNAME": "AMIGO", "NDATA": len(cov)},
    )
    common = {"DATE-OBS": date, "ARRNAME": arrname, "INSNAME": insname, "CORRNAME": "AMIGO"}
    vis2_hdu = table(
        [
            fits.Column("TARGET_ID", "I", array=np.ones(n_b, int)),
            fits.Column("TIME", "D", unit="s", array=np.zeros(n_b)),
            fits.Column("MJD", "D", unit="day", array=np.full(n_b, mjd)),
            fits.Column("INT_TIME", "D", unit="s", array=np.full(n_b, int_time_s)),
            fits.Column("VIS2DATA", "D", array=v2),
            fits.Column("VIS2ERR", "D", array=v2_err),
            fits.Column("UCOORD", "D", unit="m", array=uv_sky[:, 0]),
            fits.Column("VCOORD", "D", unit="m", array=uv_sky[:, 1]),
            fits.Column("STA_INDEX", "2I", array=pairs + 1),
            fits.Column("FLAG", "L", array=np.zeros(n_b, bool)),
            fits.Column("CORRINDX_VIS2DATA", "J", array=np.arange(1, n_b + 1)),
        ],
        "OI_VIS2",
        common,
    )
    tri = np.array(closure_triangles())
    pair_index = {p: n for n, p in enumerate(niriss.baseline_pairs())}
    uv1 = np.array([uv_sky[pair_index[(a, b)]] for a, b, _ in tri])
    uv2 = np.array([uv_sky[pair_index[(b, c)]] for _, b, c in tri])
    n_t = len(tri)
    t3_hdu = table(
        [
            fits.Column("TARGET_ID", "I", array=np.ones(n_t, int)),
            fits.Column("TIME", "D", unit="s", array=np.zeros(n_t)),
            fits.Column("MJD", "D", unit="day", array=np.full(n_t, mjd)),
            fits.Column("INT_TIME", "D", unit="s", array=np.full(n_t, int_time_s)),
            fits.Column("T3AMP", "D", array=np.full(n_t, np.nan)),
            fits.Column("T3AMPERR", "D", array=np.full(n_t, np.nan)),
            fits.Column("T3PHI", "D", unit="deg", array=cp_deg),
            fits.Column("T3PHIERR", "D", unit="deg", array=cp_err_deg),
            fits.Column("U1COORD", "D", unit="m", array=uv1[:, 0]),
            fits.Column("V1COORD", "D", unit="m", array=uv1[:, 1]),
            fits.Column("U2COORD", "D", unit="m", array=uv2[:, 0]),
            fits.Column("V2COORD", "D", unit="m", array=uv2[:, 1]),
            fits.Column("STA_INDEX", "3I", array=tri + 1),
            fits.Column("FLAG", "L", array=np.zeros(n_t, bool)),
            fits.Column("CORRINDX_T3PHI", "J", array=np.arange(n_b + 1, n_b + n_t + 1)),
        ],
        "OI_T3",
        common,
    )
    hdul = fits.HDUList([primary, target_hdu, array_hdu, wave_hdu, corr_hdu, vis2_hdu, t3_hdu])
    path = Path(path)
    with atomic_path(path) as tmp:
        hdul.writeto(tmp)
    return path
