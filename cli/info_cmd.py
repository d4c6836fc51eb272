"""``terrainmap info``: what a log or image folder holds and what ``process`` would use."""

from __future__ import annotations

import json
import math
import sys

import click

from .options import NO_PAIRS, counted, damaged_parts
from .source_options import SourceOptions, open_options


def _value(value) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    return "-" if value is None else str(value)


def format_description(description: dict) -> str:
    """``Source.describe()`` as aligned text: scalars as ``key: value``, tables and sections indented."""
    lines = []
    width = max(len(key) for key in description) + 1
    for key, value in description.items():
        label = f"{key.replace('_', ' ')}:".ljust(width + 1)
        if isinstance(value, dict):
            lines.append(label.rstrip())
            lines += [f"  {k}: {_value(v)}" for k, v in value.items()]
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            lines.append(label.rstrip())
            columns = list(value[0])
            widths = [max(len(_value(row[c])) for row in value) for c in columns]
            lines += ["  " + "  ".join(_value(row[c]).ljust(w) for c, w in zip(columns, widths, strict=True)).rstrip()
                      for row in value]
        else:
            lines.append(f"{label}{_value(value)}")
    return "\n".join(lines)


@click.command()
@click.argument("log", type=click.Path())
@open_options
@click.option("--json", "as_json", is_flag=True, help="Print the description as JSON.")
@click.option(
    "--check", is_flag=True,
    help="Also read and decode every stereo pair process would read (no matching) and say whether the "
    "log reads to its end (CRCs of the chunks that hold them, images, calibration, which must suit "
    "matching with the default settings; chunks of other topics "
    "only are not read); exit code 1 if it does not, anything was skipped, the log is damaged (damage:) or "
    "it holds no stereo pair.",
)
def info(log: str, source_opts: SourceOptions, as_json: bool, check: bool) -> None:
    """Describe LOG (an MCAP file, rosbag2 or ROS 1 bag, or an image folder): topics, the chosen
    stereo pair, calibration and extrinsics. A log without a stereo pair (terrainmap's own output,
    say) is described too, with the reason process cannot use it."""
    from terrainmap.errors import InputError, NoStereoError

    readable = True
    try:
        with source_opts.open(log) as source:
            description = source.describe()
            if check:
                from terrainmap.stereo import check_matchable

                pairs, calibration = 0, None
                try:
                    for frame in source.frames():
                        if calibration is None or frame.calibration.key() != calibration.key():
                            check_matchable(frame.calibration)  # process's checks of it: sizes, disparity range
                            calibration = frame.calibration
                        pairs += 1
                    description["check"] = f"{counted(pairs, 'stereo pair')} read and decoded, to the end"
                    skipped = source.skipped()
                    if pairs == 0:  # stereo topics, but no left and right images that pair up
                        readable = False
                        if not skipped:
                            description["check"] += f" ({NO_PAIRS})"
                    if skipped:
                        readable = False
                        description["check"] += f", skipping {damaged_parts(skipped)}"
                    if description.get("damage"):  # read whole all the same: a summary that fails its CRC
                        readable = False
                        if description["damage"] not in "; ".join(skipped):  # not the parts named above
                            description["check"] += ", but the log is damaged (see damage)"
                except InputError as exc:
                    readable = False
                    description["check"] = f"fails after {counted(pairs, 'stereo pair')}: {_reason(exc, log)}"
                if as_json:  # for scripts, every part skipped ([] for none)
                    description["skipped"] = source.skipped()
    except NoStereoError as exc:
        if (source_opts.left_topic or source_opts.right_topic) and not exc.contents.get("damage"):
            raise  # the topics the user named are not in the log: a bad option (damage may hide them)
        description = {**exc.contents, "stereo_pair": f"none, so process cannot use it ({_reason(exc, log)})"}
        if check:
            readable, description["check"] = False, "fails: no stereo pair to read"
    click.echo(json.dumps(_json_safe(description), indent=2) if as_json else format_description(description))
    if not readable:
        sys.exit(1)


def _reason(exc: Exception, log: str) -> str:
    """The error's message without the path it starts with (the description shows the path)."""
    return str(exc).removeprefix(f"{log}: ")


def _json_safe(value):
    """NaN and infinities (a broken calibration) as null: JSON has no such numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _json_safe(v) for key, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value
