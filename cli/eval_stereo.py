"""``terrainmap eval stereo``: the stereo front end's disparities against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import click

from terrainmap.config import load_config

from .options import (
    Failed,
    check_outputs,
    config_options,
    counted,
    failures,
    output_file,
    write_text,
)


@click.command("stereo")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option("--calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Calibration file to use instead of the folder's own.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Score at most this many pairs.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(".json"),
              help="Write the report as JSON.")
@config_options
def stereo(path, calibration, max_frames, json_path, config_path, overrides):
    """Score terrainmap's disparities (SGBM and its filters, as `process` runs them) against the
    ground truth of PATH: a KITTI stereo folder (disp_occ_0/), Middlebury scenes (disp0GT.pfm)
    or a log written by `terrainmap simulate` (its depth truth). Coverage, median and mean
    error, bias, shares over 1 and 3 px and KITTI's D1, by band of true depth; definitions in
    terrainmap.evaluation.disparity.
    """
    from terrainmap.evaluation.disparity import evaluate_disparity, format_table

    check_outputs({"--json": json_path}, [path, calibration, config_path])
    config = load_config(config_path, overrides)
    report = evaluate_disparity(path, config, max_frames=max_frames, calibration=calibration)
    click.echo(format_table(report))
    if report["pairs"] == 0:  # nothing to write: every metric would be null
        why = [w for w in (failures(report["failed_frames"]),
                           report["skipped"] and f"{counted(len(report['skipped']), 'pair')} damaged and skipped") if w]
        if report["pairs_without_truth"] or not why:
            why.append(f"{counted(report['pairs_without_truth'], 'pair')} without ground truth")
        raise Failed(f"no stereo pair of {path} could be scored ({', '.join(why)})")
    if not report["bands"]["all"]["truth_pixels"]:
        raise Failed(f"no stereo pair of {path} could be scored (the ground truth of its "
                     f"{counted(report['pairs'], 'pair')} holds no valid disparity)")
    if json_path:
        write_text(json_path, json.dumps(report, indent=2) + "\n")
