"""``amigo info FILE...``: identify and validate files, one row per file."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from amigo.io.identify import FileSummary, summarise

COLUMNS = ("file", "kind", "target", "filter", "groups x ints", "peak", "PA(+y)", "verdict")


def _row(summary: FileSummary) -> tuple[str, ...]:
    pa = "-" if summary.pa_y_deg is None else f"{summary.pa_y_deg:.2f}"
    return (
        summary.path.name,
        summary.kind,
        summary.target or "-",
        summary.filter or "-",
        summary.groups_x_ints or "-",
        summary.peak or "-",
        pa,
        summary.verdict,
    )


def format_table(rows: list[tuple[str, ...]]) -> str:
    """Left-aligned plain-text table (stable for scripts: columns separated by 2 spaces)."""
    widths = [max(len(r[i]) for r in [COLUMNS, *rows]) for i in range(len(COLUMNS))]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
        for r in [COLUMNS, *rows]
    ]
    return "\n".join(lines)


@click.command("info")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
def command(files: tuple[Path, ...]) -> None:
    """Identify and validate JWST NIRISS AMI files (uncal, cal, calints, rateints,
    calslope, calvis, OIFITS).

    Prints one row per file: kind, target, filter, groups x integrations, peak signal,
    the sky position angle (deg east of north) of detector +y, and a verdict. Exits with
    status 2 after listing all files if any is invalid.
    """
    summaries = [summarise(path) for path in files]
    click.echo(format_table([_row(s) for s in summaries]))
    bad = [s for s in summaries if not s.valid]
    for s in bad:
        click.echo(f"amigo: error: {s.path}: {s.verdict.removeprefix('invalid: ')}", err=True)
    if bad:
        sys.exit(2)
