"""``amigo simulate SCENARIO --out DIR [--seed N] [--noise-seed M] [--full]``: simulated
raw AMI ramps."""

from __future__ import annotations

import click


@click.command("simulate")
@click.argument("scenario")
@click.option(
    "--out", "out_dir", required=True, type=click.Path(file_okay=False),
    help="Output folder (created): DIR/<stem>_uncal.fits and DIR/<stem>_truth.json.",
)  # fmt: skip
@click.option(
    "--seed",
    default=0,
    show_default=True,
    type=click.IntRange(min=0),
    help="Master random seed: the same seed gives identical files.",
)
@click.option(
    "--noise-seed",
    default=None,
    type=click.IntRange(min=0),
    help="Draw the exposures' noise (photon and dark shot noise, reset, read and 1/f noise, "
    "cosmic rays) from this seed, keeping "
    "the telescope and detector that --seed draws [default: all from --seed].",
)
@click.option(
    "--full",
    is_flag=True,
    help="Simulate the program's numbers of integrations (the paper's photon "
    "counts) instead of the quick defaults.",
)
@click.option(
    "--only",
    "only",
    multiple=True,
    metavar="STEM",
    help="Simulate only the exposure(s) whose file stem starts with STEM "
    "(repeatable); the others' random streams are still reserved.",
)
def command(
    scenario: str,
    out_dir: str,
    seed: int,
    noise_seed: int | None,
    full: bool,
    only: tuple[str, ...],
) -> None:
    """Simulate raw ramps of SCENARIO (a built-in name or a TOML file).

    Built-in scenarios: cal4481, com1093, go1843 (copy their TOML from amigo/data/scenarios
    to make your own; see docs/simulate.md).
    """
    from amigo.pipeline import simulate

    for item in simulate(scenario, out_dir, seed=seed, full=full, only=only, noise_seed=noise_seed):
        click.echo(f"{item.uncal}\t{item.truth}")
