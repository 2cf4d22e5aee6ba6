"""A small, independent raw-ramp generator and uncal writer for the processing tests.

Deliberately simple and separate from amigo's own simulator: Poisson photo-electrons,
Gaussian read noise per group, a bias, optional cosmic-ray steps, and the ADC integral
non-linearity applied to the analog signal before quantisation to integer counts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits

GAIN_E_PER_DN = 1.61


@dataclass
class Ramps:
    """Simulated ramps and their truth.

    raw: (N, G, ny, nx) integer-valued float64 raw counts; flux_dn: (ny, nx) expected DN
    per group; bias_dn: (ny, nx); hit_group: (N, ny, nx) first group after a cosmic-ray
    step (-1 where none); hit_dn: its amplitude.
    """

    raw: np.ndarray
    flux_dn: np.ndarray
    bias_dn: np.ndarray
    hit_group: np.ndarray
    hit_dn: np.ndarray


def simulate(
    rng: np.random.Generator,
    nints: int,
    ngroups: int,
    flux_dn: np.ndarray,
    bias_dn: np.ndarray | float = 10000.0,
    read_dn: float = 10.0,
    adc: bool = True,
    cosmic_rate: float = 0.0,
    cosmic_dn: tuple[float, float] = (300.0, 3000.0),
) -> Ramps:
    flux_dn = np.asarray(flux_dn, dtype=float)
    shape = (nints, ngroups, *flux_dn.shape)
    bias = np.broadcast_to(np.asarray(bias_dn, dtype=float), flux_dn.shape)
    electrons = rng.poisson(flux_dn * GAIN_E_PER_DN, shape)
    analog = bias + np.cumsum(electrons, axis=1) / GAIN_E_PER_DN
    analog = analog + rng.normal(0.0, read_dn, shape)
    hit = rng.random((nints, *flux_dn.shape)) < cosmic_rate
    # (a hit after the last group, possible with one group, changes nothing)
    hit_group = np.where(hit, rng.integers(1, max(ngroups, 2), hit.shape), -1)
    hit_dn = np.where(hit, rng.uniform(*cosmic_dn, hit.shape), 0.0)
    groups = np.arange(ngroups)[None, :, None, None]
    analog = analog + np.where(
        (hit_group[:, None] >= 0) & (groups >= hit_group[:, None]), hit_dn[:, None], 0.0
    )
    if adc:  # the ADC's error is periodic in the counts it outputs
        analog = analog + 2.0 * np.sin(2.0 * np.pi * analog / 1024.0)
    raw = np.clip(np.rint(analog), 0, 65535)
    return Ramps(raw, flux_dn, bias, hit_group, hit_dn)


PRIMARY_KEYWORDS: dict[str, object] = {
    "TELESCOP": "JWST",
    "INSTRUME": "NIRISS",
    "DETECTOR": "NIS",
    "FILTER": "F480M",
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
    "TARGNAME": "TEST-STAR",
    "PROGRAM": "01093",
    "OBSERVTN": "012",
    "VISIT": "001",
    "EXPOSURE": "00001",
    "DATE-OBS": "2022-04-22",
    "TIME-OBS": "06:04:23.000",
    "DATAMODL": "Level1bModel",
}
SCI_KEYWORDS: dict[str, object] = {
    "BUNIT": "DN",
    "ROLL_REF": 171.8,
    "V3I_YANG": 0.56126717,
    "VPARITY": -1,
    "PA_APER": 172.36126717,
}


def write_uncal(path: Path, raw: np.ndarray, **primary: object) -> Path:
    """Write ``raw`` (N, G, 80, 80) as an uncal file: SCI uint16 stored as int16 + BZERO."""
    header = fits.Header()
    for key, value in {**PRIMARY_KEYWORDS, **primary}.items():
        header[key] = value
    header.setdefault("NINTS", raw.shape[0])
    header.setdefault("NGROUPS", raw.shape[1])
    sci = fits.ImageHDU(np.asarray(raw).astype(np.uint16), name="SCI")
    for key, value in SCI_KEYWORDS.items():
        sci.header[key] = value
    fits.HDUList([fits.PrimaryHDU(header=header), sci]).writeto(path, overwrite=True)
    return path
