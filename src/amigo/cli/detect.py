"""``amigo detect FILE... --out DIR``: companion search, posteriors and contrast limits."""

from __future__ import annotations

from pathlib import Path

import click

from amigo.errors import InputError


@click.command(name="detect")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder (created if needed).",
)
@click.option(
    "--rmax-mas",
    type=click.FloatRange(min=1.0),
    default=1000.0,
    show_default=True,
    help="Search radius (mas).",
)
@click.option(
    "--threshold",
    type=click.FloatRange(min=0.0, min_open=True),
    default=5.0,
    show_default=True,
    help="Detection threshold (Gaussian-equivalent sigma).",
)
@click.option(
    "--step-mas",
    type=click.FloatRange(min=0.1),
    default=None,
    help="Grid step (mas); default lambda_min / (3 B_max).",
)
@click.option(
    "--max-companions",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    help="Stop after this many companions.",
)
@click.option(
    "--observables",
    type=click.Choice(["all", "phase", "amplitude"]),
    default="all",
    show_default=True,
    help="Observables to fit: all, phase-type only (kernel or closure phases: for OIFITS "
    "whose V2 are poorly calibrated) or amplitude-type only.",
)
@click.option(
    "--cp-correlation",
    type=click.Choice(["baseline", "independent"]),
    default="baseline",
    show_default=True,
    help="OIFITS closure phases without covariance: correlated through shared "
    "baselines, or independent.",
)
@click.option(
    "--primary-diameter-mas",
    type=click.FloatRange(min=0.0),
    default=0.0,
    show_default=True,
    help="Uniform-disc diameter of the primary (0: unresolved).",
)
@click.option("--no-hmc", is_flag=True, help="Skip NUTS; report least-squares (Laplace) errors.")
@click.option("--no-per-filter", is_flag=True, help="Skip the per-filter fits.")
@click.option(
    "--warmup",
    type=click.IntRange(min=10),
    default=500,
    show_default=True,
    help="NUTS warm-up steps per chain.",
)
@click.option(
    "--samples",
    type=click.IntRange(min=10),
    default=1000,
    show_default=True,
    help="NUTS samples per chain.",
)
@click.option(
    "--chains", type=click.IntRange(min=1), default=2, show_default=True, help="NUTS chains."
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed of NUTS.")
@click.option(
    "--force",
    is_flag=True,
    help="Search again [default: keep the products in DIR when its companions.json records "
    "the same input files, options and version].",
)
def command(
    files,
    out_dir,
    rmax_mas,
    threshold,
    step_mas,
    max_companions,
    observables,
    cp_correlation,
    primary_diameter_mas,
    no_hmc,
    no_per_filter,
    warmup,
    samples,
    chains,
    seed,
    force=False,
) -> None:
    """Search calibrated observables (calvis or OIFITS FILEs) for companions.

    Writes DIR/companions.json, DIR/contrast_limits.csv and figures (DIR/*.png).
    """
    options = dict(locals())  # the parameters, before any other name is bound
    settings = {k: v for k, v in options.items() if k not in ("files", "out_dir", "force")}
    key = _detect_key(files, settings)
    if not force and _up_to_date(Path(out_dir), key):
        click.echo(
            f"{Path(out_dir) / 'companions.json'}: up to date (same inputs and options), "
            "kept (--force searches again)"
        )
        return
    import jax

    # Fits, Hessians and HMC need float64. A context rather than the global switch, so a
    # process that calls this command (tests, notebooks) keeps its own precision after.
    with jax.enable_x64(True):
        _detect(
            files,
            out_dir,
            rmax_mas,
            threshold,
            step_mas,
            max_companions,
            observables,
            cp_correlation,
            primary_diameter_mas,
            no_hmc,
            no_per_filter,
            warmup,
            samples,
            chains,
            seed,
            key,
        )


def _detect_key(files, settings: dict) -> str:
    """Identity of a search: 16 hex characters of the SHA-256 of the amigo version, the
    options and the input files' names and content fingerprints."""
    import hashlib
    import json

    from amigo._version import __version__
    from amigo.io.files import fingerprint, require_file

    inputs = [(Path(f).name, fingerprint(require_file(f, "input file"))) for f in files]
    text = json.dumps(
        {"version": __version__, "settings": settings, "inputs": inputs}, sort_keys=True
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _up_to_date(out: Path, key: str) -> bool:
    """Whether ``out`` holds a complete search with identity ``key``: companions.json,
    written last, records it, and contrast_limits.csv is there."""
    import json

    try:
        document = json.loads((out / "companions.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (
        isinstance(document, dict)
        and document.get("detect_key") == key
        and (out / "contrast_limits.csv").is_file()
    )


def _detect(
    files,
    out_dir,
    rmax_mas,
    threshold,
    step_mas,
    max_companions,
    observables,
    cp_correlation,
    primary_diameter_mas,
    no_hmc,
    no_per_filter,
    warmup,
    samples,
    chains,
    seed,
    key: str = "",
) -> None:
    from amigo.companions import observables as obs
    from amigo.companions import plots, products
    from amigo.companions.search import SearchSettings, detect
    from amigo.progress import step

    blocks = [obs.load(f, cp_correlation=cp_correlation, observables=observables) for f in files]
    for path, block in zip(files, blocks, strict=True):
        step(f"{path}: {block.filter_name}, {block.n_obs} observables, {block.n_uv} uv points")
    dataset = obs.Dataset.from_blocks(blocks)
    if step_mas is not None and step_mas >= rmax_mas:
        raise InputError(
            None, f"--step-mas ({step_mas}) must be smaller than --rmax-mas ({rmax_mas})"
        )
    settings = SearchSettings(
        rmax_mas=rmax_mas,
        step_mas=step_mas,
        threshold_sigma=threshold,
        max_companions=max_companions,
        primary_diameter_mas=primary_diameter_mas,
        hmc=not no_hmc,
        per_filter=not no_per_filter,
        num_warmup=warmup,
        num_samples=samples,
        num_chains=chains,
        seed=seed,
    )
    result = detect(dataset, settings)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # companions.json last: a search interrupted before it is not taken for complete.
    products.write_contrast_csv(out / "contrast_limits.csv", result)
    plots.write_all(result, out)
    products.write_companions_json(
        out / "companions.json", result, list(files), {"detect_key": key}
    )

    if not result.companions:
        click.echo(f"no companion above {threshold:g} sigma within {rmax_mas:g} mas")
    for c in result.companions:
        e = c.estimate
        dmag = ", ".join(f"{f} {e.dmag[f]:.3f}±{e.dmag_err[f]:.3f}" for f in dataset.filters)
        click.echo(
            f"companion {c.id}: sep {e.sep_mas:.2f}±{e.sep_err_mas:.2f} mas, "
            f"PA {e.pa_deg:.2f}±{e.pa_err_deg:.2f} deg, dmag {dmag}, "
            f"{c.detection_sigma:.1f} sigma ({c.method}"
            + (
                ""
                if c.significance is None
                else f"; false-alarm probability {c.significance.false_alarm_probability:.2g}"
            )
            + ")"
        )
    for r in result.rejected:
        click.echo(f"not a detection: {r.note}")
    scales = ", ".join(f"{f} {v:.2f}" for f, v in result.sigma_scale.items())
    click.echo(f"sigma_scale: {scales}")
    for message in result.warnings:
        click.echo(f"warning: {message}", err=True)
    click.echo(f"wrote {out / 'companions.json'}, {out / 'contrast_limits.csv'} and figures")
