"""``terrainmap bench``: per-stage timings (a benchmark, never a test)."""

from __future__ import annotations

import json

import click

from terrainmap.config import load_config

from .options import check_outputs, config_options, output_file, write_text
from .source_options import SourceOptions, open_options


@click.command()
@click.option("--runs", type=click.IntRange(1, 10_000), default=30, show_default=True, help="Timed runs per stage.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), callback=output_file(),
              help='Write {stage: {median_ms, ...}, "process": {median_fps, ...}} here.')
@click.option("--log", "log_path", type=click.Path(exists=True),
              help="Time the stages on the first stereo pair of this log or folder instead of synthetic input.")
@click.option("--process-frames", type=click.IntRange(0, 100_000), default=40, show_default=True,
              help="Then time `process` (reading and writing included) three times over this many stereo pairs: "
                   "the --log's first ones, or a still simulated log's (0: skip).")
@open_options
@config_options
def bench(
    runs: int, json_path: str | None, log_path: str | None, process_frames: int, source_opts: SourceOptions,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Time each pipeline stage at the paper configuration on synthetic input (or on a log's first
    pair), then the throughput of `process`."""
    from terrainmap import bench as lib

    check_outputs({"--json": json_path}, [config_path, log_path, source_opts.calibration])
    source_opts.require(log_path, "--log")
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
        rate = lib.process_rate(config, log_path, frames=process_frames, **source_opts.open_kwargs())
        results["process"] = rate
        where = f"the first {rate['frames']} stereo pairs of {log_path}" if log_path else (
            f"{rate['frames']} pairs of a still simulated log")
        click.echo(f"process, frames/s over {where}, {rate['runs']} runs: median {rate['median_fps']:.1f}, "
                   f"min {rate['min_fps']:.1f}, max {rate['max_fps']:.1f}")
        click.echo(_goal_line("process, frames/s (median)", rate["median_fps"], 15.0, at_most=False))
    if json_path:
        write_text(json_path, json.dumps(results, indent=2) + "\n")


def _goal_line(what: str, value: float, limit: float, *, at_most: bool) -> str:
    """``what: value (meets|MISSES the goal of at most|least limit)``, with as many decimals as
    show why it meets or misses: not "1.60 (MISSES the goal of at most 1.6)"."""
    def meets(v: float) -> bool:
        return v <= limit if at_most else v >= limit

    digits = next((d for d in range(2, 10) if meets(value) == meets(round(value, d))), None)
    shown = repr(value) if digits is None else f"{value:.{digits}f}"
    bound = "at most" if at_most else "at least"
    return f"{what}: {shown} ({'meets' if meets(value) else 'MISSES'} the goal of {bound} {limit:g})"
