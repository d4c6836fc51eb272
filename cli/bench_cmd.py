"""``terrainmap bench``: per-stage timings (a benchmark, never a test)."""

from __future__ import annotations

import json

import click

from terrainmap.config import load_config
from terrainmap.errors import TerrainmapError, counted

from .options import check_outputs, config_options, failures, output_file, write_text
from .source_options import SourceOptions, open_options

STILL_FRAMES = 1000
"""The most pairs of the still simulated log that bench writes to time process."""
MIN_RATE_FRAMES = 10
"""The fewest pairs whose process rate is held to the goal."""


@click.command()
@click.option("--runs", type=click.IntRange(1, 10_000), default=30, show_default=True, help="Timed runs per stage.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(".json"),
              help='Write {stage: {median_ms, ...}, "process": {median_fps, ...}} here.')
@click.option("--log", "log_path", type=click.Path(exists=True),
              help="Time the stages on the first stereo pair of this log or folder instead of synthetic input.")
@click.option("--process-frames", type=click.IntRange(0, 100_000), default=40, show_default=True,
              help="Then time process (reading and writing included) three times over this many stereo pairs: "
                   f"the --log's first ones, or a still simulated log's (at most {STILL_FRAMES}; 0: skip).")
@open_options
@config_options
def bench(
    runs: int, json_path: str | None, log_path: str | None, process_frames: int, source_opts: SourceOptions,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Time each pipeline stage at the paper configuration on synthetic input (or on a log's first
    pair), then the throughput of process."""
    from terrainmap import bench as lib

    check_outputs({"--json": json_path}, [config_path, log_path, source_opts.calibration])
    source_opts.require(log_path, "--log")
    if process_frames > STILL_FRAMES and not log_path:  # (the still log takes about 1 MB a frame)
        raise click.BadParameter(f"at most {STILL_FRAMES} without --log, got {process_frames}",
                                 param_hint="--process-frames")
    config = load_config(config_path, overrides)
    env = lib.environment()
    click.echo("machine: " + ", ".join(f"{k}={v}" for k, v in env.items()))
    frame = None
    if log_path:
        frame = lib.first_frame(log_path, **source_opts.open_kwargs())
        click.echo(f"input: the first stereo pair of {log_path}, {frame.left.shape[1]}×{frame.left.shape[0]}")
    results = lib.run(config, runs=runs, stages=lib.all_stages(config, frame))
    click.echo(f"{'stage':<18}{'median ms':>10}{'min ms':>10}{'max ms':>10}{'runs':>6}")
    for name, r in results.items():
        click.echo(f"{name:<18}{r['median_ms']:10.2f}{r['min_ms']:10.2f}{r['max_ms']:10.2f}{r['runs']:6d}")
    for what, value, limit in lib.goals(results):
        click.echo(_goal_line(what, value, limit, at_most=True))
    if process_frames:
        _time_process(config, log_path, process_frames, source_opts, frame, results)
    if json_path:
        write_text(json_path, json.dumps(results, indent=2) + "\n")


def _time_process(config, log_path, frames: int, source_opts: SourceOptions, frame, results: dict) -> None:
    """Time process over ``frames`` pairs (bench.process_rate), print the rate and, for pairs of
    640×480 that all gave terrain, at least MIN_RATE_FRAMES of them, hold it to the goal; add it
    to ``results`` as "process". An error in the log's later pairs is said in one line: the stage
    timings stand."""
    from terrainmap import bench as lib

    try:
        rate = lib.process_rate(config, log_path, frames=frames, **source_opts.open_kwargs())
    except TerrainmapError as exc:
        click.echo(f"process: not timed ({exc})")
        return
    results["process"] = rate
    size = (640, 480) if frame is None else (frame.left.shape[1], frame.left.shape[0])
    where = (f"the first {counted(rate['frames'], 'stereo pair')} of {log_path}" if log_path
             else f"{rate['frames']} pairs of a still simulated log")
    click.echo(f"process, frames/s over {where} ({size[0]}×{size[1]}), {rate['runs']} runs: median "
               f"{rate['median_fps']:.1f}, min {rate['min_fps']:.1f}, max {rate['max_fps']:.1f}")
    if rate["failed"]:
        click.echo(f"process: {sum(rate['failed'].values())} of those pairs failed ({failures(rate['failed'])}), "
                   "so the rate is not held to the goal")
    elif size != (640, 480):
        click.echo("process: the goal of at least 15 frames/s is set at 640×480, so the rate is not held to it")
    elif rate["frames"] < MIN_RATE_FRAMES:
        click.echo(f"process: fewer than {MIN_RATE_FRAMES} pairs (the first builds the matcher, the workers fill), "
                   "so the rate is not held to the goal")
    else:
        click.echo(_goal_line("process, frames/s (median)", rate["median_fps"], 15.0, at_most=False))


def _goal_line(what: str, value: float, limit: float, *, at_most: bool) -> str:
    """``what: value (meets|MISSES the goal of at most|least limit)``, with as many decimals as
    show why it meets or misses: not "1.60 (MISSES the goal of at most 1.6)"."""
    def meets(v: float) -> bool:
        return v <= limit if at_most else v >= limit

    digits = next((d for d in range(2, 10) if meets(value) == meets(round(value, d))), None)
    shown = repr(value) if digits is None else f"{value:.{digits}f}"
    bound = "at most" if at_most else "at least"
    return f"{what}: {shown} ({'meets' if meets(value) else 'MISSES'} the goal of {bound} {limit:g})"
