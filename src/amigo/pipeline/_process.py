"""The work of ``amigo process`` (:func:`amigo.pipeline.process`): raw ramps -> calslope.

Each file is processed on its own: a bad input is reported in one line naming it and the
others are still processed; a file whose calslope product is complete and records the
same input, options and version is kept unless ``force``.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from amigo.errors import InputError


@dataclass
class ProcessResult:
    """What :func:`amigo.pipeline.process` did.

    Attributes
    ----------
    written
        Calslope files written by this call.
    kept
        Calslope files left as they were (complete, same input and options).
    failed
        Input file -> the problem (one line), for the files that could not be processed.
    """

    written: list[Path] = field(default_factory=list)
    kept: list[Path] = field(default_factory=list)
    failed: dict[Path, str] = field(default_factory=dict)

    @property
    def calslope(self) -> list[Path]:
        """Every calslope product of the call (written or kept), in input order."""
        return [*self.written, *self.kept]


def process(
    uncal: Sequence[str | Path],
    out: str | Path,
    *,
    sigma: float = 3.0,
    adc: bool = True,
    saturation_dn: float | None = None,
    one_over_f: str = "stripes",
    force: bool = False,
) -> ProcessResult:
    """Raw ramps (``_uncal.fits``) to ``out/<stem>_calslope.fits``, as ``amigo process``.

    ``sigma``: outlier clipping threshold (robust standard deviations); ``adc``: correct
    the ADC's integral non-linearity; ``saturation_dn``: raw count of saturation
    (default the ADC full scale); ``one_over_f``: ``"stripes"`` removes 1/f column
    offsets, ``"none"`` leaves them; ``force``: process files whose product is already
    complete. A bad file is reported (``ProcessResult.failed``) and the others go on.
    """
    from amigo.io.calslope import calslope_name, is_up_to_date
    from amigo.processing.ramps import SATURATION_DN, ProcessSettings, process_file
    from amigo.progress import track

    out = Path(out)
    settings = ProcessSettings(
        nsigma=sigma,
        adc_correction=adc,
        saturation_dn=SATURATION_DN if saturation_dn is None else saturation_dn,
        one_over_f=one_over_f,
    )
    result = ProcessResult()
    claimed: dict[str, Path] = {}
    for path in map(Path, uncal):
        name = calslope_name(path)

        def progress(
            items: Iterable[object], total: int, stage: str, _label: str = path.name
        ) -> Iterable[object]:
            return track(items, f"process {_label}: {stage}", total=total)

        try:
            if name in claimed:
                raise InputError(path, f"writes the same {name} as {claimed[name]}")
            claimed[name] = path
            if (
                not force
                and path.is_file()
                and is_up_to_date(out / name, path, settings.header_cards())
            ):
                print(f"{out / name}: up to date, skipped (--force processes it again)")
                result.kept.append(out / name)
                continue
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                written, product = process_file(path, out, settings, progress=progress)
            # The reader validates the file on each pass: say each note once.
            for message in dict.fromkeys(str(warning.message) for warning in caught):
                print(f"amigo: note: {message}", file=sys.stderr)
        except InputError as error:
            print(f"amigo: error: {error}", file=sys.stderr)
            result.failed[path] = error.problem
            continue
        result.written.append(written)
        nbad = int(product.badpix.sum())
        print(
            f"{written}: {product.nints} integrations x {product.ramp_dn.shape[0]} groups, "
            f"{nbad} bad pixels"
        )
    return result
