"""``terrainmap eval accuracy``: terrainmap and the baselines against a simulated log's ground truth."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from terrainmap.config import load_config

from .options import (
    PLOT_SUFFIXES,
    Failed,
    Finite,
    check_outputs,
    config_options,
    failures,
    output_file,
    write_text,
    writing,
)


@click.command("accuracy")
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--methods", default=None, metavar="NAME,...",
              help="Comma-separated methods (default: every available one: terrainmap and the baselines).")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Evaluate at most this many frames.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(".json"),
              help="Write the report as JSON.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), callback=output_file(*PLOT_SUFFIXES),
              help="Draw elevation RMSE against range for each method to this image (.png, .pdf or .svg).")
@click.option("--obstacle-margin", type=Finite(min=0), default=0.5, show_default=True,
              help="A track matches a true obstacle when its centre lies in the true footprint grown by this, m.")
@config_options
def accuracy(log, methods, max_frames, json_path, plot_path, obstacle_margin, config_path, overrides):
    """Score elevation, slope, coverage, terrain segmentation and obstacles per range band
    on LOG, a log written by `terrainmap simulate` (it carries the ground truth).

    Every method runs on the same stereo points of each frame; the definitions of the metrics
    are in terrainmap.evaluation.accuracy.
    """
    from terrainmap.errors import ConfigError
    from terrainmap.evaluation.accuracy import evaluate, select_methods
    from terrainmap.evaluation.accuracy_report import format_table, plot_rmse_vs_range

    check_outputs({"--json": json_path, "--plot": plot_path}, [log, config_path])
    config = load_config(config_path, overrides)
    names = [m.strip() for m in methods.split(",") if m.strip()] if methods is not None else None
    try:
        names = select_methods(names)
    except ConfigError as exc:
        raise click.BadParameter(str(exc).removeprefix("--methods: "), param_hint="--methods") from None
    show = sys.stderr.isatty()
    report = evaluate(log, config, methods=names, max_frames=max_frames, obstacle_margin_m=obstacle_margin,
                      progress=(lambda n: click.echo(f"\rframe {n}", nl=False, err=True)) if show else None)
    if show:
        click.echo(err=True)
    click.echo(format_table(report))
    click.echo(f"\nwall time {report['seconds']['wall']:.1f} s")
    if report["frames"] == 0:  # nothing to write: every metric would be null
        raise Failed(f"no frame of {log} could be scored ({failures(report['failed_frames']) or 'no frame read'})")
    if json_path:
        write_text(json_path, json.dumps(report, indent=2) + "\n")
    if plot_path:
        with writing(plot_path) as partial:
            plot_rmse_vs_range(report, str(partial))
