"""``terrainmap simulate``: render a simulated off-road stereo drive with ground truth."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from terrainmap.errors import ConfigError
from terrainmap.sim.scenes import SCENES

from .options import Finite, GracefulStop, check_outputs, counted, output_file, wrote_before_stopping


@click.command()
@click.argument("out", type=click.Path(), callback=output_file())
@click.option("--scene", type=click.Choice(SCENES), default="mounds", show_default=True, help="Terrain and obstacles.")
@click.option("--frames", type=int, default=50, show_default=True, help="Number of stereo frames, 1..100000.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed, 0..2^32-1 (same seed, same log).")
@click.option("--format", "fmt", type=click.Choice(["mcap", "folder"]), default=None,
              help="Output layout [default: mcap when OUT ends in .mcap, else folder].")
@click.option("--width", type=int, default=640, show_default=True, help="Image width, 32..4096 pixels.")
@click.option("--height", type=int, default=480, show_default=True, help="Image height, 16..4096 pixels.")
@click.option("--focal-px", type=Finite(), default=500.0, show_default=True, help="Focal length, 1..10^6 pixels.")
@click.option("--baseline-m", type=Finite(), default=0.3, show_default=True, help="Stereo baseline, 0.001..100 metres.")
@click.option("--camera-height-m", type=Finite(), default=1.8, show_default=True, help="Camera above the ground, metres (> 0).")
@click.option("--pitch-deg", type=Finite(), default=6.0, show_default=True, help="Camera pitch down, -30..45 degrees.")
@click.option("--noise", type=Finite(), default=2.0, show_default=True, help="Pixel noise σ, 0..50 grey levels.")
@click.option("--vignetting", type=Finite(), default=0.15, show_default=True, help="Darkening at the corners, in [0, 1).")
@click.option("--texture-detail", type=Finite(), default=1.0, show_default=True,
              help="Fine texture kept with range, 0.25..8 (2: about a pixel's box filter, no other blur).")
@click.option("--speed-mps", type=Finite(), default=4.0, show_default=True, help="Vehicle speed, 0..40 m/s.")
@click.option("--fps", type=Finite(), default=10.0, show_default=True, help="Frame rate, Hz (> 0).")
@click.option("--color/--mono", default=False, show_default=True, help="rgb8 or mono8 images.")
@click.option("--compressed", is_flag=True, help="MCAP: PNG CompressedImage camera topics instead of raw Image.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def simulate(out: Path, fmt: str | None, overwrite: bool, **options) -> None:
    """Render a stereo drive over a procedural off-road SCENE and write it to OUT.

    OUT is a ROS 2 MCAP log (camera images, camera_info, /tf, /tf_static) with the ground truth
    on /truth/... topics, or an image folder (left/, right/, timestamps.txt, calibration.yaml)
    with truth/. Read the truth with terrainmap.sim.open_truth.
    """
    from terrainmap.sim import SimConfig
    from terrainmap.sim import simulate as run

    fmt = fmt or ("mcap" if out.suffix.lower() == ".mcap" else "folder")
    check_outputs({"OUT": out}, [])  # first: neither file nor folder (a FIFO) is refused there
    if out.exists() and not overwrite and (out.is_file() or any(out.iterdir())):
        raise click.UsageError(f"{out} exists; pass --overwrite to replace it")
    if fmt == "mcap" and out.is_dir():
        raise click.UsageError(f"{out} is a folder; an MCAP output must be a file")
    if fmt == "folder" and out.is_file():
        raise click.UsageError(f"{out} is a file; a folder output must be a folder")
    config = SimConfig(format=fmt, **options)
    try:
        config.validate()
    except ConfigError as exc:  # SimConfig's fields are the options: name the option the user gave
        field, _, reason = str(exc).partition(": ")
        raise ConfigError(f"--{field.removeprefix('SimConfig.').replace('_', '-')}: {reason}") from None

    written = 0

    def progress(index: int) -> None:
        nonlocal written
        written = index + 1
        bar.update(1)
        stop.check()  # between frames: the log written so far is finalised

    with GracefulStop() as stop, click.progressbar(length=config.frames, label=f"simulate {config.scene}",
                                                   file=sys.stderr, hidden=not sys.stderr.isatty()) as bar:
        with stop.outputs_open():
            try:
                summary = run(out, config, progress=progress)
            except KeyboardInterrupt:
                click.echo("\n" + wrote_before_stopping([(written, out)]))
                raise
    click.echo(
        f"wrote {counted(summary['frames'], 'frame')} ({config.width}×{config.height}, scene {config.scene}, seed {config.seed}) "
        f"to {summary['path']}: {summary['bytes'] / 1e6:.1f} MB in {summary['seconds']:.1f} s"
    )
