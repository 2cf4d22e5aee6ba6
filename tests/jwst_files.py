"""Write small synthetic JWST NIRISS AMI files for tests (astropy only, like STScI files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import fits

PRIMARY_KEYWORDS = {
    "TELESCOP": "JWST",
    "INSTRUME": "NIRISS",
    "DETECTOR": "NIS",
    "FILTER": "F430M",
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
    "TARGPROP": "TEST-STAR",
    "TARGNAME": "HD 1",
    "PROGRAM": "04481",
    "OBSERVTN": "001",
    "VISIT": "001",
    "EXPOSURE": "1",
    "DATE-OBS": "2024-05-05",
    "TIME-OBS": "12:00:00.000",
}
SCI_KEYWORDS = {"ROLL_REF": 100.0, "V3I_YANG": 0.56126717, "VPARITY": -1, "PA_APER": 100.56126717}


def _headers(overrides: dict | None, drop: tuple[str, ...]) -> tuple[fits.Header, fits.Header]:
    primary = fits.Header()
    sci = fits.Header()
    for key, value in PRIMARY_KEYWORDS.items():
        primary[key] = value
    for key, value in SCI_KEYWORDS.items():
        sci[key] = value
    for key, value in (overrides or {}).items():
        (sci if key in SCI_KEYWORDS else primary)[key] = value
    for key in drop:
        primary.remove(key, ignore_missing=True)
        sci.remove(key, ignore_missing=True)
    return primary, sci


def write_uncal(
    path: Path,
    ramps: np.ndarray,
    overrides: dict | None = None,
    drop: tuple[str, ...] = (),
) -> Path:
    """Write (nints, ngroups, ny, nx) counts as a level-1b uncal file (uint16 via BZERO)."""
    nints, ngroups = ramps.shape[:2]
    primary, sci = _headers({"NINTS": nints, "NGROUPS": ngroups, **(overrides or {})}, drop)
    primary["DATAMODL"] = "Level1bModel"
    hdus = fits.HDUList(
        [fits.PrimaryHDU(header=primary), fits.ImageHDU(ramps.astype(np.uint16), sci, name="SCI")]
    )
    hdus.writeto(path, overwrite=True)
    return path


def write_level2(
    path: Path,
    sci_data: np.ndarray,
    err: np.ndarray | None = None,
    dq: np.ndarray | None = None,
    overrides: dict | None = None,
    drop: tuple[str, ...] = (),
) -> Path:
    """Write a level-2 cal/calints-like file (SCI/ERR float32 DN/s, DQ uint32)."""
    nints = 1 if sci_data.ndim == 2 else sci_data.shape[0]
    primary, sci = _headers({"NINTS": nints, "NGROUPS": 5, **(overrides or {})}, drop)
    sci["BUNIT"] = "DN/s"
    err = np.ones_like(sci_data) if err is None else err
    dq = np.zeros(sci_data.shape, np.uint32) if dq is None else dq
    hdus = fits.HDUList(
        [
            fits.PrimaryHDU(header=primary),
            fits.ImageHDU(sci_data.astype(np.float32), sci, name="SCI"),
            fits.ImageHDU(err.astype(np.float32), name="ERR"),
            fits.ImageHDU(dq.astype(np.uint32), name="DQ"),
        ]
    )
    hdus.writeto(path, overwrite=True)
    return path


def nominal_star(filter_name: str = "F480M", flux_dn_s: float = 2e5) -> np.ndarray:
    """(80, 80) DN/s: a point source (0.03, -0.02 pixels off the reference position,
    ``flux_dn_s`` entering the mask) through amigo's nominal instrument at 3 wavelengths,
    with its nominal jitter; no noise."""
    import jax.numpy as jnp

    from amigo.model.image import (
        ExposureParams,
        FilterSetup,
        Instrument,
        OpticsParams,
        image_from_log_vis,
    )

    instrument = Instrument.nominal(n_wavelengths=3)
    setup = FilterSetup.create(filter_name, instrument)
    exposure = ExposureParams(
        jnp.asarray([0.03, -0.02], jnp.float32),
        jnp.log(jnp.float32(flux_dn_s)),
        jnp.float32(float(instrument.detector.jitter_arcsec) * 1000.0),
    )
    optics = OpticsParams.from_instrument(instrument)
    image = image_from_log_vis(instrument, setup, optics, 0.0, exposure, None, None)
    return np.asarray(image, dtype=float)
