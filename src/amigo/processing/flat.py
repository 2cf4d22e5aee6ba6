"""Flat-field exposures (``PUPIL`` CLEARP, ``EXP_TYPE`` NIS_LAMP) -> calslope files.

``amigo process`` refuses them (they are not AMI data), but training uses them to separate
the pixels' response from the PSF (:mod:`amigo.training.trainer`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import fits

from amigo.errors import InputError
from amigo.io.calslope import calslope_name, write_calslope
from amigo.processing.ramps import ArraySource, check_usable, process_ramps


def process_flat_field(uncal_path: str | Path, out_dir: str | Path) -> Path:
    """Process a flat-field (uniformly illuminated, ``PUPIL`` CLEARP / ``EXP_TYPE``
    NIS_LAMP) raw-ramp file into a calslope file, exactly as ``amigo process`` does for
    AMI exposures (which it refuses: flats are not AMI data, but training needs them).
    """
    path = Path(uncal_path)
    try:
        with fits.open(path, memmap=False) as hdul:
            primary, sci = hdul[0].header.copy(), hdul["SCI"].header.copy()
            raw = np.asarray(hdul["SCI"].data, dtype=np.float64)
    except Exception as error:  # astropy raises several types for damaged files
        raise InputError(path, f"cannot be read as a raw-ramp file ({error})") from None
    if raw.ndim != 4:
        raise InputError(path, f"SCI has shape {raw.shape}, expected (nints, ngroups, ny, nx)")
    product = process_ramps(ArraySource(raw))
    check_usable(path, product)
    out = Path(out_dir) / calslope_name(path)
    write_calslope(out, product, primary, sci, uncal_name=path.name)
    return out
