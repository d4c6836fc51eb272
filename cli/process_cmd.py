"""``terrainmap process``: the main job — a stereo log or folder in, terrain layers out."""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import click

from terrainmap.config import load_config

from .options import (
    NO_PAIRS,
    Failed,
    GracefulStop,
    check_outputs,
    config_options,
    counted,
    damaged_parts,
    failures,
    output_file,
    wrote_before_stopping,
)
from .source_options import source_options


def default_output(log: Path) -> Path:
    """``run.mcap`` → ``run.terrain.mcap`` beside it; a folder ``d/`` → ``d.terrain.mcap`` beside it.
    A file of a rosbag2 folder (one with ``metadata.yaml``) → beside the folder, not in it, where
    the output would become one more file of the recording. A symbolic link counts where it is, not
    where it points: a link into a read-only dataset store gets its output beside the link."""
    log = Path(os.path.abspath(log))  # `.` and `..` get their names; links are not followed
    stem = log.name if log.is_dir() else log.stem
    folder = log.parent.parent if log.is_file() and (log.parent / "metadata.yaml").is_file() else log.parent
    return folder / f"{stem}.terrain.mcap"


@click.command()
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False), callback=output_file(".mcap"), help="Output MCAP (default: <log>.terrain.mcap beside the input).")
@click.option("--flavor", type=click.Choice(["foxglove", "ros2"]), default="foxglove", show_default=True,
              help="Message family of the MCAP: Foxglove protobuf schemas or ROS 2 messages (GridMap, PointCloud2).")
@click.option("--compression", type=click.Choice(["lz4", "zstd", "none"]), default="lz4", show_default=True,
              help="MCAP chunk compression.")
@click.option("--rrd", type=click.Path(dir_okay=False), callback=output_file(".rrd"), help="Also write a Rerun recording here.")
@click.option("--overwrite", is_flag=True, help="Replace existing output files.")
@source_options
@config_options
def process(log, output, flavor, compression, rrd, overwrite, source_opts, config_path, overrides):
    """Run the terrain pipeline on every stereo pair of LOG (MCAP, rosbag2 folder, ROS 1 bag or image folder)
    and write elevation, slope, labels, obstacles and cost to an MCAP (and optionally Rerun)."""
    from terrainmap import runner
    from terrainmap.sinks import open_mcap_sink
    from terrainmap.sources import log_path
    from terrainmap.stereo import check_matchable

    log = log_path(log)  # a rosbag2's metadata.yaml: its folder, for the default output's name too
    config = load_config(config_path, overrides)
    output = output or default_output(log)
    _check_process_outputs(log, output, rrd, overwrite, [source_opts.calibration, config_path])
    show = sys.stderr.isatty()
    outputs = [output] + ([rrd] if rrd else [])
    progress = []  # the run's summary, kept to tell what was written when the run fails

    def on_frame(summary, frame, result) -> None:
        progress[:] = [summary]
        if show:
            _progress(summary, frame, result)
        stop.check()  # between frames: a signal never cuts an output in the middle of a write

    with GracefulStop() as stop, source_opts.open(str(log)) as source:
        frames = source.frames(**source_opts.frames_kwargs())
        # The first frame is read before any output is opened: a bad selection, a missing
        # calibration or an empty selection then fails without touching an earlier output.
        first = next(frames, None)
        if first is None:
            raise Failed(f"no frame of {log} could be processed ({_why_none(source)})")
        check_matchable(first.calibration, config.stereo)  # images it cannot match: refused before any output
        stop.check()  # a signal while the first frame was read: no earlier output is replaced
        frames = itertools.chain([first], frames)
        with stop.outputs_open():
            sinks = [open_mcap_sink(output, flavor, config=config, metadata={"source": str(log)}, compression=compression)]
            if rrd is not None:
                from terrainmap.sinks.rerun_recording import RerunSink

                try:
                    sinks.append(RerunSink(rrd, config=config))
                except BaseException:
                    sinks[0].close()
                    raise
            try:
                summary = runner.run(frames, config, sinks, on_frame=on_frame)
            except BaseException:
                if show:
                    click.echo(err=True)  # ends the progress line
                finished = [sink for sink in sinks if sink.finished]  # what they hold reads back
                if any(sink.frames_written for sink in finished):  # each its own: one may have failed mid-frame
                    click.echo(wrote_before_stopping([(sink.frames_written, sink.path) for sink in finished]))
                raise
            if show:
                click.echo(err=True)
    _report(summary, outputs, source.skipped())
    if summary.frames_done == 0:
        raise Failed(f"no frame of {log} could be processed ({failures(summary.failures, summary.first_failures)})")
    stop.check()  # a signal while the outputs were being closed: the exit code still says so


def _check_process_outputs(log: Path, output: Path, rrd: Path | None, overwrite: bool, inputs: list) -> None:
    """Outputs must not replace an input (the log, a file inside a log folder, the calibration or
    config file) nor each other, nor replace an existing file without ``--overwrite``."""
    if output.is_dir():  # (-o is refused as a folder by click; the default output beside the log is not)
        raise click.UsageError(f"{output} (the default output) is a folder; name a file with -o")
    check_outputs({"-o/--output": output, "--rrd": rrd}, [log, *inputs])
    for path in (output, rrd):
        if path is not None and path.exists() and not overwrite:
            raise click.UsageError(f"{path} exists; pass --overwrite to replace it")


def _progress(summary, frame, result) -> None:
    click.echo(
        f"\rframe {frame.index}: {summary.frames_done} done, {summary.frames_failed} failed, "
        f"{_fps(summary.fps)} frames/s ",
        err=True,
        nl=False,
    )


def _fps(rate: float) -> str:
    """Frames/s to one decimal, or two significant digits below 1 (a huge image's 0.04)."""
    return f"{rate:.2g}" if rate < 0.95 else f"{rate:.1f}"


def _why_none(source) -> str:
    """Why ``source.frames()`` gave no frame: no pairs, none in the selection, or damage."""
    tally, skipped = source.tally, source.skipped()
    if tally.pairs == 0:
        why = NO_PAIRS
    elif tally.selected == 0:
        why = (f"--start/--end select none of the {counted(tally.pairs, 'stereo pair')} read, up to "
               f"{max(tally.span_s, 0.0):.3f} s from the first (--start and --end count from it)")
    else:
        why = f"every one of the {counted(tally.selected, 'stereo pair')} selected is damaged"
    if skipped:
        why += f"; {counted(len(skipped), 'damaged part')} skipped, the first: {skipped[0]}"
    return why


def _report(summary, outputs, skipped: list[str]) -> None:
    from terrainmap.extrinsics import describe_extrinsics

    first = summary.first_failures if summary.frames_done else None  # (else the error line after it says it)
    failed = f", {summary.frames_failed} failed ({failures(summary.failures, first)})" if summary.frames_failed else ""
    rate = f" ({_fps(summary.fps)} frames/s)" if summary.frames_done else ""
    click.echo(f"processed {counted(summary.frames_done, 'frame')}{failed} in {summary.wall_s:.1f} s{rate}")
    if skipped:
        click.echo(f"skipped {damaged_parts(skipped)}")
    medians = summary.median_ms()
    if medians:
        click.echo("median ms per frame: " + ", ".join(f"{k} {v:.1f}" for k, v in medians.items()))
    if summary.extrinsics is not None:
        pose = describe_extrinsics(summary.extrinsics)
        click.echo(
            f"camera pose ({summary.extrinsics.source}): height {pose['height_m']:.2f} m, "
            f"pitch {pose['pitch_deg']:.1f}°, roll {pose['roll_deg']:.1f}°"
        )
    empty = " (no frame in it)" if summary.frames_done == 0 else ""
    for path in outputs:
        click.echo(f"wrote {path}{empty}")
