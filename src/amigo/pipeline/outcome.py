"""What ``amigo fit`` reports per filter, and which filters a re-run can keep.

Every filter of a fit ends in one of four statuses, recorded in ``fit_summary.json`` (per
filter and per exposure) and summed up by the exit status of the command
(docs/reliability.md):

``"ok"``
    fitted and converged; its calvis and OIFITS files are written.
``"unconverged"``
    fitted, but the convergence tests did not pass: products written and flagged
    (``CONVERGD = F`` in the calvis header).
``"failed"``
    a numerical failure (:class:`amigo.errors.NumericalFailure`: a singular matrix,
    values that are not finite, no usable DISCO) or no usable exposure left in a role:
    no products; ``"problem"`` says why.
``"excluded"`` (exposures only)
    the exposure has no usable star (every pixel flagged, or no flux above its noise);
    the filter was fitted without it.

Re-running the same command keeps the filters whose products are complete and record the
same inputs and settings (:func:`fit_key`); ``--force`` fits them again.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from amigo.errors import InputError

#: Exit status when some filters have products and others failed, or exposures were
#: left out (fit_summary.json says which).
EXIT_PARTIAL = 3
#: Exit status when no filter has products (every one failed; fit_summary.json says why).
EXIT_NO_PRODUCT = 4

USABLE = ("ok", "unconverged")


def fit_key(settings: Mapping[str, Any], exposures: Sequence[tuple[str, str, str]]) -> str:
    """Identity of one filter's fit: 16 hex characters of the SHA-256 of the settings
    (JSON-serialisable: version, model, options) and of the ``(role, target,
    file fingerprint)`` of its exposures, in the order fitted."""
    text = json.dumps({"settings": settings, "exposures": list(exposures)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def previous_summary(out: Path) -> dict[str, Any]:
    """The ``fit_summary.json`` already in ``out``, or ``{}`` where there is none or it
    does not parse (then nothing is kept)."""
    path = out / "fit_summary.json"
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return summary if isinstance(summary, dict) else {}


def kept_records(
    out: Path, filter_name: str, key: str, summary: Mapping[str, Any]
) -> tuple[dict, list[dict]] | None:
    """The filter's and its exposures' records from a previous summary, when its fit is
    complete and made from the same inputs: the recorded key equals ``key``, the status
    is usable, and every product it lists reads back (calvis files with the same
    ``FITKEY``). ``None``: fit it."""
    from amigo.io.calvis import read_calvis
    from amigo.io.oifits import read_oifits

    filters = summary.get("filters")
    record = filters.get(filter_name) if isinstance(filters, dict) else None
    if not isinstance(record, dict) or record.get("fit_key") != key:
        return None
    products = record.get("products")
    if record.get("status") not in USABLE or not isinstance(products, list) or not products:
        return None
    for name in products:
        path = out / str(name)
        try:
            if path.name.endswith("_calvis.fits"):
                if read_calvis(path).header.get("FITKEY") != key:
                    return None
            else:
                read_oifits(path)
        except InputError:
            return None
    exposures = [
        e
        for e in summary.get("exposures", [])
        if isinstance(e, dict) and e.get("filter") == filter_name
    ]
    return (record, exposures) if exposures else None


def exit_status(filters: Mapping[str, Mapping[str, Any]], exposures: Sequence[Mapping]) -> int:
    """0: every filter has products and every exposure was used; :data:`EXIT_PARTIAL`:
    some have products; :data:`EXIT_NO_PRODUCT`: none has."""
    usable = [f for f in filters.values() if f.get("status") in USABLE]
    if not usable:
        return EXIT_NO_PRODUCT
    if len(usable) < len(filters) or any(e.get("status") == "excluded" for e in exposures):
        return EXIT_PARTIAL
    return 0
