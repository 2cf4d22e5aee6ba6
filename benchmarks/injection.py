"""Sky angles on real data: a companion injected through a file's own WCS, recovered by
``amigo fit`` and ``amigo detect`` (prints a table).

    python benchmarks/injection.py [--science FILE] [--calibrator FILE] [--sep-mas 328.85]
                                   [--pa 280.5 100.5 190.5 10.5] [--dmag 4.381] [--out DIR]

A real single star's level-2 image (default: HD 36805, COM 1093 obs 18, F480M) gets a
copy of itself, scaled by the flux ratio and shifted to a companion's position: the sky
offset (separation, position angle east of north) goes through the image's own FITS WCS
(astropy, as docs/orientation.md defines the convention) to a detector offset in pixels,
and the copy is shifted by it in Fourier space (F480M's image is Nyquist sampled by the
mask's longest baseline, so the shift is that of the illuminance; the pixels' response
moves with it). The new file is fitted against a real calibrator (default: HD 37093, obs
15, F480M) and searched with ``amigo detect --no-hmc``. What comes back is compared with
what went in: none of amigo's geometry is used to place the companion, so a rotation or
a flip of the sky in amigo's chain (the detector geometry, the orientation keywords, the
calibrators' fitted distortions) shows as a position-angle error common to every row.
About a minute per row on a 2-core CPU (warm). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
DATA = SHARED / "data" / "jwst"
SCIENCE = DATA / "com1093-calibrators" / "jw01093018001_03102_00001_nis_cal.fits"
CALIBRATOR = DATA / "com1093" / "jw01093015001_03102_00001_nis_cal.fits"


def inject(source: Path, out: Path, sep_mas: float, pa_deg: float, ratio: float) -> tuple:
    """Write ``source`` plus ``ratio`` times its own image shifted to the companion's
    position (``sep_mas``, ``pa_deg`` east of north) to ``out``; return the detector
    offset ``(dx, dy)`` in pixels. NaN pixels stay NaN; ERR and DQ are kept (the copy adds
    ~2 % to the photon noise at most, below what the fit's error scale measures)."""
    import astropy.units as u
    from astropy.io import fits
    from astropy.wcs import WCS
    from scipy.ndimage import fourier_shift

    with fits.open(source) as hdul:
        copy = fits.HDUList([h.copy() for h in hdul])
    sci = np.asarray(copy["SCI"].data, float)
    good = np.isfinite(sci)
    image = np.where(good, sci, 0.0)
    # The star's photocentre in a 9 x 9 box around its peak (the WCS's reference point).
    y, x = np.indices(image.shape)
    peak = np.unravel_index(np.argmax(np.where(good, image, -np.inf)), image.shape)
    box = image * ((abs(y - peak[0]) <= 4) & (abs(x - peak[1]) <= 4))
    x0, y0 = float((box * x).sum() / box.sum()), float((box * y).sum() / box.sum())
    wcs = WCS(copy["SCI"].header)
    star = wcs.pixel_to_world(x0, y0)
    companion = star.directional_offset_by(pa_deg * u.deg, sep_mas * u.mas)
    xc, yc = wcs.world_to_pixel(companion)
    dx, dy = float(xc) - x0, float(yc) - y0
    shifted = np.fft.ifft2(fourier_shift(np.fft.fft2(image), (dy, dx))).real
    copy["SCI"].data = np.where(good, image + ratio * shifted, np.nan).astype(np.float32)
    copy.writeto(out, overwrite=True)
    return dx, dy


def _amigo(*args: object) -> None:
    subprocess.run([sys.executable, "-m", "amigo", *map(str, args)], check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--science", type=Path, default=SCIENCE, help="a single star's file")
    parser.add_argument("--calibrator", type=Path, default=CALIBRATOR)
    parser.add_argument("--sep-mas", type=float, default=328.85)
    parser.add_argument("--pa", type=float, nargs="+", default=[280.5, 100.5, 190.5, 10.5])
    parser.add_argument("--dmag", type=float, default=4.381)
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: temp)")
    args = parser.parse_args(argv)
    if not (args.science.exists() and args.calibrator.exists()):
        print(f"files not found ({args.science}, {args.calibrator}): set AMIGO_SHARED")
        return 1
    out = args.out or Path(tempfile.mkdtemp(prefix="amigo-injection-"))
    out.mkdir(parents=True, exist_ok=True)
    ratio = 10 ** (-0.4 * args.dmag)
    print(f"# {args.science.name} + companion (sep {args.sep_mas} mas, dmag {args.dmag}) "
          f"against {args.calibrator.name}; amigo fit, amigo detect --no-hmc")  # fmt: skip
    print("| PA in (deg) | offset dx, dy (px) | sep out (mas) | PA out (deg) | d PA (deg, sigma) "
          "| dmag out | sigma_scale |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    errors = []
    for i, pa in enumerate(args.pa):
        # A file name of the JWST form, one observation number per row (the fit keys
        # exposures by name, and the calibrator's must differ).
        injected = out / f"jw0109399{i:02d}01_03102_00001_nis_cal.fits"
        dx, dy = inject(args.science, injected, args.sep_mas, pa, ratio)
        fit, search = out / f"fit{i}", out / f"detect{i}"
        _amigo("fit", "--sci", injected, "--cal", args.calibrator, "--out", fit, "--force")
        _amigo("detect", *sorted(fit.glob("*_calvis.fits")), "--out", search, "--force",
               "--no-hmc")  # fmt: skip
        found = json.loads((search / "companions.json").read_text()) if search.exists() else {}
        if not found.get("companions"):
            print(f"| {pa:.1f} | {dx:+.3f}, {dy:+.3f} | not found | | | | |")
            continue
        c = found["companions"][0]
        d_pa = (c["pa_deg"] - pa + 180.0) % 360.0 - 180.0
        errors.append(d_pa)
        dmag = ", ".join(f"{v:.3f}" for v in c["dmag"].values())
        scale = ", ".join(f"{v:.2f}" for v in found["sigma_scale"].values())
        print(f"| {pa:.1f} | {dx:+.3f}, {dy:+.3f} | {c['sep_mas']:.2f} +- {c['sep_err_mas']:.2f} "
              f"| {c['pa_deg']:.2f} +- {c['pa_err_deg']:.2f} | {d_pa:+.2f} "
              f"({d_pa / c['pa_err_deg']:+.1f}) | {dmag} | {scale} |")  # fmt: skip
    if errors:
        e = np.asarray(errors)
        print(f"\nmean PA error {e.mean():+.3f} deg over {e.size} rows "
              f"(scatter {e.std(ddof=1) if e.size > 1 else float('nan'):.3f} deg)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
