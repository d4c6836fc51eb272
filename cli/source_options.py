"""Source options shared by ``info`` and ``process``, defined once.

``@open_options`` adds ``--left-topic``, ``--right-topic``, ``--calibration`` and
``--pair-tolerance-ms``; ``@source_options`` adds those and the frame selection ``--start``,
``--end``, ``--every``, ``--max-frames``. Either collects them into one ``source_opts:
SourceOptions`` argument of the command::

    @click.command()
    @click.argument("log")
    @source_options
    def process(log, source_opts):
        with source_opts.open(log) as source:
            for frame in source.frames(**source_opts.frames_kwargs()):
                ...
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import click

from .options import Finite

_OPEN_NAMES = ("left_topic", "right_topic", "calibration", "pair_tolerance_ms")
_FRAME_NAMES = ("start", "end", "every", "max_frames")


@dataclass(frozen=True)
class SourceOptions:
    """The source options of a command line, turned into ``open_source``/``frames`` kwargs."""

    left_topic: str | None = None
    right_topic: str | None = None
    calibration: str | None = None
    pair_tolerance_ms: float = 10.0
    start: float | None = None
    end: float | None = None
    every: int = 1
    max_frames: int | None = None

    def open_kwargs(self) -> dict:
        """Keyword arguments of :func:`terrainmap.sources.open_source`."""
        return {
            "left_topic": self.left_topic,
            "right_topic": self.right_topic,
            "calibration": self.calibration,
            "pair_tolerance_ns": round(self.pair_tolerance_ms * 1e6),
        }

    def frames_kwargs(self) -> dict:
        """Keyword arguments of :meth:`terrainmap.sources.Source.frames`."""
        return {"start_s": self.start, "end_s": self.end, "every": self.every, "max_frames": self.max_frames}

    def require(self, source, option: str) -> None:
        """Refuse the open options (UsageError) when ``source``, the value of ``option`` that they
        apply to, is not given: they would be ignored."""
        ctx = click.get_current_context()
        given = [f"--{name.replace('_', '-')}" for name in _OPEN_NAMES
                 if ctx.get_parameter_source(name) not in (None, click.core.ParameterSource.DEFAULT)]
        if given and not source:
            raise click.UsageError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for the log of {option}; "
                                   f"give {option} too")

    def open(self, path: str):
        """Open ``path`` with these options (imports the sources package lazily)."""
        from terrainmap.sources import open_source

        return open_source(path, **self.open_kwargs())


def _collect(func: Callable, names: tuple[str, ...]) -> Callable:
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        values = {name: kwargs.pop(name) for name in names}
        return func(*args, source_opts=SourceOptions(**values), **kwargs)

    return wrapper


def _add_open_options(func: Callable) -> Callable:
    func = click.option(
        "--pair-tolerance-ms", type=Finite(min=0, max=3_600_000), default=10.0, show_default=True,
        help="Largest stamp difference of a left/right image pair in a log, milliseconds.",
    )(func)
    func = click.option(
        "--calibration", type=click.Path(exists=True, dir_okay=False), default=None,
        help="Calibration file (YAML/TOML, KITTI or Middlebury calib.txt) overriding the source's own.",
    )(func)
    func = click.option("--right-topic", default=None, help="Right image topic of a log (default: guessed).")(func)
    return click.option("--left-topic", default=None, help="Left image topic of a log (default: guessed).")(func)


def open_options(func: Callable) -> Callable:
    """``--left-topic``, ``--right-topic``, ``--calibration``, ``--pair-tolerance-ms`` → ``source_opts``."""
    return _add_open_options(_collect(func, _OPEN_NAMES))


def source_options(func: Callable) -> Callable:
    """:func:`open_options` plus ``--start``, ``--end``, ``--every``, ``--max-frames`` → ``source_opts``."""
    func = _collect(func, _OPEN_NAMES + _FRAME_NAMES)
    func = click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Process at most this many frames.")(func)
    func = click.option("--every", type=click.IntRange(min=1), default=1, show_default=True,
                        help="Keep every N-th stereo pair.")(func)
    func = click.option("--end", type=Finite(min=0), default=None, help="End (inclusive), seconds after the first stereo pair's stamp.")(func)
    func = click.option("--start", type=Finite(min=0), default=None,
                        help="Start (inclusive), seconds after the first stereo pair's stamp.")(func)
    return _add_open_options(func)
