"""Simulated calibrated observables for the companion-detection tests.

Everything here is written with plain NumPy, independently of amigo.companions, so that
the tests compare the library against a separate implementation of the same physics:

* a calvis-like DISCO matrix from the real 21 NIRISS baselines: kernel amplitudes (null
  space of hole gains) and kernel phases (null space of hole pistons), randomly rotated;
* binary visibilities ``V = (1 + c sum_l w_l exp(-2 pi i b.theta/lambda_l)) / (1 + c)``;
* OIFITS files with V2 and closure phases whose noise comes from independent noise on the
  baseline phases (so closure phases are correlated as in real data).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from astropy.io import fits

from amigo import niriss
from amigo.io.calvis import nominal_sky_to_uv, write_calvis
from amigo.orientation import Orientation

MAS = np.pi / (180 * 3600 * 1000)


def null_space_rows(matrix: np.ndarray) -> np.ndarray:
    """Orthonormal rows spanning the left null space of ``matrix`` (rows K with K A = 0)."""
    u, s, _ = np.linalg.svd(matrix, full_matrices=True)
    rank = int(np.sum(s > 1e-10 * s.max()))
    return u[:, rank:].T


def uv_points(splodge_radius_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """uv points (m) and the baseline (0..20) each belongs to.

    With ``splodge_radius_m = 0`` the 21 baselines; otherwise each baseline plus six points
    around it, as a forward model samples the extended splodge of two 0.8 m holes.
    """
    baselines = niriss.baselines_m()
    if splodge_radius_m == 0:
        return baselines, np.arange(len(baselines))
    angles = np.deg2rad(np.arange(6) * 60.0 + 15.0)
    ring = splodge_radius_m * np.column_stack([np.cos(angles), np.sin(angles)])
    offsets = np.vstack([[0.0, 0.0], ring])
    points = (baselines[:, None, :] + offsets[None]).reshape(-1, 2)
    return points, np.repeat(np.arange(len(baselines)), len(offsets))


def kernel_disco_matrix(rng: np.random.Generator, owner: np.ndarray | None = None) -> np.ndarray:
    """Map from [log|V|, arg V] at the uv points to independent kernel observables.

    Kernel amplitudes: the left null space of the hole-gain Jacobian; kernel phases: of the
    hole-piston Jacobian (every point of a splodge inherits its baseline's row); each
    randomly rotated. For the 21 baselines alone: (14 + 15, 42).
    """
    pairs = np.array(niriss.baseline_pairs())
    owner = np.arange(len(pairs)) if owner is None else owner
    n_b = len(owner)
    gains = np.zeros((n_b, niriss.N_HOLES))
    pistons = np.zeros((n_b, niriss.N_HOLES))
    gains[np.arange(n_b), pairs[owner, 0]] = 1.0
    gains[np.arange(n_b), pairs[owner, 1]] = 1.0
    pistons[np.arange(n_b), pairs[owner, 0]] = -1.0
    pistons[np.arange(n_b), pairs[owner, 1]] = 1.0
    k_amp = null_space_rows(gains)  # (n_b - 7, n_b)
    k_phase = null_space_rows(pistons)  # (n_b - 6, n_b)
    # A random rotation inside each kernel: a different, non-sparse basis (like DISCOs).
    q_amp, _ = np.linalg.qr(rng.normal(size=(k_amp.shape[0],) * 2))
    q_phase, _ = np.linalg.qr(rng.normal(size=(k_phase.shape[0],) * 2))
    d = np.zeros((k_amp.shape[0] + k_phase.shape[0], 2 * n_b))
    d[: k_amp.shape[0], :n_b] = q_amp @ k_amp
    d[k_amp.shape[0] :, n_b:] = q_phase @ k_phase
    return d


def binary_visibility(uv_m, wavelengths_m, weights, offsets_uv_mas, contrasts):
    """Band-averaged complex visibility of a point primary and point companions.

    ``offsets_uv_mas`` (K, 2) are angular offsets in the same frame as ``uv_m``.
    """
    uv_m = np.asarray(uv_m)
    total = np.ones(len(uv_m), dtype=complex)
    for (tx, ty), c in zip(np.atleast_2d(offsets_uv_mas), np.atleast_1d(contrasts), strict=True):
        path = (uv_m[:, 0] * tx + uv_m[:, 1] * ty) * MAS
        phasor = np.zeros(len(uv_m), dtype=complex)
        for lam, w in zip(wavelengths_m, weights, strict=True):
            phasor += w * np.exp(-2j * np.pi * path / lam)
        total += c * phasor
    return total / (1.0 + np.sum(contrasts))


def write_sim_calvis(
    path: Path,
    filter_name: str,
    companions: list[tuple[float, float, float]],
    rng: np.random.Generator,
    error: float = 2e-3,
    pa_aper_deg: float = 172.3,
    target: str = "SIM-STAR",
    splodge_radius_m: float = 0.0,
    silent_rows: int = 0,
) -> Path:
    """A calvis file of one filter with companions ``(dRA mas, dDec mas, flux ratio)``.

    ``splodge_radius_m > 0`` samples each splodge at 7 uv points (see :func:`uv_points`).
    ``silent_rows``: that many more observables that no sky moves (zero rows of the
    matrix, pure noise), drawn from their own generator: the others are those of the
    same call without them.
    """
    bins = niriss.filter_bins(filter_name, 5)
    uv, owner = uv_points(splodge_radius_m)
    d = kernel_disco_matrix(rng, owner)
    orientation = Orientation(pa_aper_deg=pa_aper_deg)
    sky_to_uv = nominal_sky_to_uv(orientation)
    if companions:
        sky = np.array([[c[0], c[1]] for c in companions])
        offsets_uv = sky @ sky_to_uv.T
        vis = binary_visibility(
            uv, bins.wavelengths_m, bins.weights, offsets_uv, np.array([c[2] for c in companions])
        )
    else:
        vis = np.ones(len(uv), dtype=complex)
    log_vis = np.concatenate([np.log(np.abs(vis)), np.angle(vis)])
    errors = error * rng.uniform(0.7, 1.3, size=d.shape[0])
    values = d @ log_vis + errors * rng.normal(size=d.shape[0])
    n_amp = len(uv) - niriss.N_HOLES
    kinds = ["amplitude"] * n_amp + ["phase"] * (d.shape[0] - n_amp)
    if silent_rows:
        extra = np.random.default_rng(99)
        d = np.vstack([d, np.zeros((silent_rows, d.shape[1]))])
        noise = np.full(silent_rows, error)
        values = np.concatenate([values, noise * extra.normal(size=silent_rows)])
        errors = np.concatenate([errors, noise])
        kinds += ["phase"] * silent_rows
    return write_calvis(
        path,
        values=values,
        errors=errors,
        kinds=kinds,
        disco_matrix=d,
        uv_m=uv,
        wavelengths_m=bins.wavelengths_m,
        weights=bins.weights,
        sky_to_uv=sky_to_uv,
        orientation=orientation,
        n_photons=1e8,
        target=target,
        filter_name=filter_name,
        science_files=[f"jw_sim_{filter_name}_cal.fits"],
        calibrator_files=[f"jw_simcal_{filter_name}_cal.fits"],
    )


def sim_dataset(
    folder: Path,
    filters: tuple[str, ...],
    companions: list[tuple[float, float, float]],
    rng: np.random.Generator,
    prefix: str = "S",
):
    """A :class:`~amigo.companions.observables.Dataset` of one calvis file per filter
    (:func:`write_sim_calvis`, splodges sampled at 7 uv points), written into ``folder``
    as ``<prefix>_<filter>_calvis.fits``."""
    from amigo.companions import observables as obs

    blocks = [
        obs.load(
            write_sim_calvis(
                folder / f"{prefix}_{f}_calvis.fits", f, companions, rng, splodge_radius_m=0.4
            )
        )
        for f in filters
    ]
    return obs.Dataset.from_blocks(blocks)


def oifits_baselines(pa_deg: float = 30.0) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """The 21 NIRISS baselines rotated onto the sky (u east, v north) and the 35 triangles."""
    holes = niriss.HOLE_CENTRES_M
    theta = np.deg2rad(pa_deg)
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return holes @ rotation.T, list(itertools.combinations(range(7), 3))


def binary_v2_cp(holes_sky, triangles, wavelength_m, band_m, dra, ddec, contrast, n_lam=7):
    """Exact V2 (21) and closure phases (35, rad) of a binary, top-hat band of ``n_lam``."""
    lams = wavelength_m + band_m * ((np.arange(n_lam) + 0.5) / n_lam - 0.5)
    weights = np.full(n_lam, 1.0 / n_lam)

    def vis(b):
        return binary_visibility(b, lams, weights, [[dra, ddec]], [contrast])

    pairs = list(itertools.combinations(range(7), 2))
    uv = np.array([holes_sky[j] - holes_sky[i] for i, j in pairs])
    v2 = np.abs(vis(uv)) ** 2
    u1 = np.array([holes_sky[b] - holes_sky[a] for a, b, _ in triangles])
    u2 = np.array([holes_sky[c] - holes_sky[b] for _, b, c in triangles])
    cp = np.angle(vis(u1) * vis(u2) * np.conj(vis(u1 + u2)))
    return uv, pairs, v2, u1, u2, cp


def write_sim_oifits(
    path: Path,
    rng: np.random.Generator,
    companion: tuple[float, float, float] | None,
    cp_error_rad: float = 2e-3,
    v2_error: float = 2e-3,
    wavelength_m: float = 4.817e-6,
    band_m: float = 2.98e-7,
    filter_name: str = "F480M",
    pa_deg: float = 30.0,
    template: Path | None = None,
) -> Path:
    """Write an OIFITS2 file (V2 + CP) of a simulated binary with realistic correlated noise.

    Closure-phase noise comes from independent noise on the 21 baseline phases with
    standard deviation ``cp_error_rad / sqrt(3)`` (so each closure phase has the quoted
    error). With ``template`` (an OIFITS file), its uv coverage, wavelength and errors are
    used instead of the NIRISS mask at ``pa_deg``.
    """
    dra, ddec, c = companion if companion else (0.0, 0.0, 0.0)
    if template is not None:
        return _write_from_template(path, rng, template, dra, ddec, c)
    holes, triangles = oifits_baselines(pa_deg)
    uv, pairs, v2, u1, u2, cp = binary_v2_cp(holes, triangles, wavelength_m, band_m, dra, ddec, c)
    phase_noise = rng.normal(size=len(pairs)) * cp_error_rad / np.sqrt(3)
    index = {p: k for k, p in enumerate(pairs)}
    cp_noise = np.array(
        [
            phase_noise[index[(a, b)]] + phase_noise[index[(b, cc)]] - phase_noise[index[(a, cc)]]
            for a, b, cc in triangles
        ]
    )
    v2_obs = v2 + v2_error * rng.normal(size=v2.size)
    cp_obs = cp + cp_noise
    stations_v2 = np.array([[i + 1, j + 1] for i, j in pairs], dtype=np.int16)
    stations_t3 = np.array([[a + 1, b + 1, cc + 1] for a, b, cc in triangles], dtype=np.int16)
    return _write_oifits(
        path,
        filter_name,
        wavelength_m,
        band_m,
        uv,
        v2_obs,
        np.full(v2.size, v2_error),
        stations_v2,
        u1,
        u2,
        cp_obs,
        np.full(cp.size, cp_error_rad),
        stations_t3,
    )


def _write_from_template(path, rng, template, dra, ddec, c):
    with fits.open(template) as hdul:
        wave = float(hdul["OI_WAVELENGTH"].data["EFF_WAVE"][0])
        band = float(hdul["OI_WAVELENGTH"].data["EFF_BAND"][0])
        v2t = hdul["OI_VIS2"].data
        t3t = hdul["OI_T3"].data
        uv = np.column_stack([v2t["UCOORD"], v2t["VCOORD"]])
        u1 = np.column_stack([t3t["U1COORD"], t3t["V1COORD"]])
        u2 = np.column_stack([t3t["U2COORD"], t3t["V2COORD"]])
        v2_err = np.asarray(v2t["VIS2ERR"], float)
        cp_err = np.deg2rad(np.asarray(t3t["T3PHIERR"], float))
        st2 = np.asarray(v2t["STA_INDEX"])
        st3 = np.asarray(t3t["STA_INDEX"])
        filter_name = hdul[0].header.get("FILT", "F480M")
    lams = wave + band * ((np.arange(7) + 0.5) / 7 - 0.5)
    w = np.full(7, 1 / 7)

    def vis(b):
        return binary_visibility(b, lams, w, [[dra, ddec]], [c])

    v2 = np.abs(vis(uv)) ** 2
    cp = np.angle(vis(u1) * vis(u2) * np.conj(vis(u1 + u2)))
    # Baseline-phase noise: closure phases correlated as the reader assumes, each with
    # (about) its quoted error.
    pairs = {tuple(sorted(p)): k for k, p in enumerate(st2.tolist())}
    sigma_b = np.median(cp_err) / np.sqrt(3)
    phase_noise = rng.normal(size=len(pairs)) * sigma_b
    cp_noise = []
    for a, b, cc in st3.tolist():
        cp_noise.append(
            phase_noise[pairs[(a, b)]] + phase_noise[pairs[(b, cc)]] - phase_noise[pairs[(a, cc)]]
        )
    return _write_oifits(
        path,
        filter_name,
        wave,
        band,
        uv,
        v2 + v2_err * rng.normal(size=v2.size),
        v2_err,
        st2,
        u1,
        u2,
        cp + np.array(cp_noise),
        cp_err,
        st3,
    )


def _write_oifits(
    path, filter_name, wave, band, uv, v2, v2_err, st2, u1, u2, cp, cp_err, st3
) -> Path:
    primary = fits.PrimaryHDU()
    primary.header["CONTENT"] = "OIFITS2"
    primary.header["TELESCOP"] = "JWST"
    primary.header["INSTRUME"] = "NIRISS"
    primary.header["FILT"] = filter_name
    wl = fits.BinTableHDU.from_columns(
        [
            fits.Column("EFF_WAVE", "E", unit="m", array=[wave]),
            fits.Column("EFF_BAND", "E", unit="m", array=[band]),
        ],
        name="OI_WAVELENGTH",
    )
    wl.header["INSNAME"] = "NIRISS"
    wl.header["OI_REVN"] = 2
    target = fits.BinTableHDU.from_columns(
        [fits.Column("TARGET_ID", "I", array=[1]), fits.Column("TARGET", "16A", array=["SIMSTAR"])],
        name="OI_TARGET",
    )
    n2, n3 = len(v2), len(cp)
    vis2 = fits.BinTableHDU.from_columns(
        [
            fits.Column("TARGET_ID", "I", array=np.ones(n2)),
            fits.Column("VIS2DATA", "D", array=v2),
            fits.Column("VIS2ERR", "D", array=v2_err),
            fits.Column("UCOORD", "D", unit="m", array=uv[:, 0]),
            fits.Column("VCOORD", "D", unit="m", array=uv[:, 1]),
            fits.Column("STA_INDEX", "2I", array=st2),
            fits.Column("FLAG", "L", array=np.zeros(n2, bool)),
        ],
        name="OI_VIS2",
    )
    vis2.header["INSNAME"] = "NIRISS"
    t3 = fits.BinTableHDU.from_columns(
        [
            fits.Column("TARGET_ID", "I", array=np.ones(n3)),
            fits.Column("T3PHI", "D", unit="deg", array=np.rad2deg(cp)),
            fits.Column("T3PHIERR", "D", unit="deg", array=np.rad2deg(cp_err)),
            fits.Column("U1COORD", "D", unit="m", array=u1[:, 0]),
            fits.Column("V1COORD", "D", unit="m", array=u1[:, 1]),
            fits.Column("U2COORD", "D", unit="m", array=u2[:, 0]),
            fits.Column("V2COORD", "D", unit="m", array=u2[:, 1]),
            fits.Column("STA_INDEX", "3I", array=st3),
            fits.Column("FLAG", "L", array=np.zeros(n3, bool)),
        ],
        name="OI_T3",
    )
    t3.header["INSNAME"] = "NIRISS"
    fits.HDUList([primary, wl, target, vis2, t3]).writeto(path, overwrite=True)
    return Path(path)


def write_point_source_oifits(
    path: Path, target: str = "SIM-STAR", error: float = 1e-2, **extra
) -> Path:
    """amigo's OIFITS file of a point source in F480M (log-amplitudes and phases 0, each
    with ``error`` rad, independent); ``extra``: :func:`amigo.io.oifits_write.write_oifits`'s
    keywords (``science_files``, ``n_photons``)."""
    from amigo.io.oifits_write import write_oifits

    return write_oifits(
        path,
        target=target,
        filter_name="F480M",
        wavelength_m=4.8e-6,
        bandwidth_m=3e-7,
        log_amp=np.zeros(21),
        phase_rad=np.zeros(21),
        covariance=error**2 * np.eye(42),
        sky_to_uv=np.eye(2),
        **extra,
    )
