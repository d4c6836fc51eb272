"""Options shared by several commands, defined once."""

from __future__ import annotations

import errno
import itertools
import math
import os
import signal
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import click

from terrainmap.errors import counted

PLOT_SUFFIXES = (".png", ".pdf", ".svg")


class Finite(click.FloatRange):
    """A float option that must also be finite: click's FloatRange lets nan and inf through."""

    name = "finite float"

    def _describe_range(self) -> str:
        return "finite" if self.min is None and self.max is None else super()._describe_range()

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number


class Failed(click.ClickException):
    """A command that could not do its job, for a reason the message gives: exit code 2, like
    the library's errors (click's own exceptions exit with 1)."""

    exit_code = 2


STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGXCPU")
                     if hasattr(signal, name))
"""The signals that end a run as Ctrl-C does: SIGTERM (a supervisor) and, where the system has
them, SIGHUP (the terminal closed or the SSH session dropped) and SIGXCPU (a soft CPU time limit,
`ulimit -St`, reached; a hard limit alone, or reached, kills the process with SIGKILL)."""

_ON_TERMINAL: dict[int, bool] = {}
"""Whether standard output and error (1, 2) were terminals when the signals were last taken over."""


def take_stop_signals(handler: Callable) -> dict:
    """Install ``handler`` for :data:`STOP_SIGNALS` and give the handlers it replaced. A signal the
    process was started ignoring (SIGINT of a `cmd &` job in a script, SIGHUP under nohup) stays
    ignored."""
    _ON_TERMINAL.update({fd: os.isatty(fd) for fd in (1, 2)})
    return {s: signal.signal(s, handler) for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN}


def leave_hung_up_terminal(signum: int) -> None:
    """After SIGHUP, point standard output and error at the null device where they were a terminal
    that is gone: every write to it would fail (EIO), the clean-up's messages included."""
    if signum != getattr(signal, "SIGHUP", None):
        return
    for fd, was_terminal in _ON_TERMINAL.items():
        if was_terminal and not os.isatty(fd):
            with suppress(OSError):
                point_at_null_device(fd)


def point_at_null_device(fd: int) -> None:
    """Make descriptor ``fd`` the null device's (open or closed before)."""
    null = os.open(os.devnull, os.O_RDWR)
    if null != fd:  # (a closed fd is the lowest free one: opening took it)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)


class GracefulStop:
    """While active, SIGINT (Ctrl-C), SIGTERM, SIGHUP and SIGXCPU (:data:`STOP_SIGNALS`) only ask the run to
    stop: :meth:`check`, called between frames, then raises KeyboardInterrupt, so that no output is
    cut in the middle of a write and every file is finalised. A second signal interrupts at once
    while no output is open (a run stuck finding its first frame); while outputs are open
    (:meth:`outputs_open`) every signal only asks, so a quick double Ctrl-C never leaves a file
    without its summary or with half a frame."""

    last_signal: int | None = None
    """The signal that stopped the last run (the CLI exits with 128 + it, as a shell expects)."""

    def __init__(self) -> None:
        self.requested = False
        self._open = 0

    def _handle(self, signum, frame) -> None:
        GracefulStop.last_signal = signum
        leave_hung_up_terminal(signum)
        if self.requested and not self._open:
            raise KeyboardInterrupt
        self.requested = True

    def check(self, *_) -> None:
        if self.requested:
            raise KeyboardInterrupt

    @contextmanager
    def outputs_open(self):
        """The block that opens, writes and closes the outputs."""
        self._open += 1
        try:
            yield
        finally:
            self._open -= 1

    def __enter__(self):
        self._previous = take_stop_signals(self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)


NO_PAIRS = "no left and right images whose stamps agree within --pair-tolerance-ms"
"""Why a log with stereo topics gives no stereo pair (``process`` and ``info --check`` say it)."""


DAMAGE_SHOWN = 3
"""How many of the damaged parts skipped a summary names (each was warned about as it was met)."""


def damaged_parts(skipped: list[str]) -> str:
    """``2 damaged parts: A; B``, or past :data:`DAMAGE_SHOWN` of them ``40 damaged parts: A; B; C;
    and 37 more (warned as they were met)``: one line however much of a long log is damaged."""
    more = len(skipped) - DAMAGE_SHOWN
    listed = "; ".join(skipped[:DAMAGE_SHOWN]) + (f"; and {more} more (warned as they were met)" if more > 0 else "")
    return f"{counted(len(skipped), 'damaged part')}: {listed}"


def failures(counts: dict[str, int], first: dict[str, str] | None = None) -> str:
    """``no_ground ×3, too_few_cells ×1``: frame failures by reason, most frequent first; with
    ``first`` (reason → its first failure's message), ``; frame 0: ...`` of the most frequent
    reason follows, where the message says more than the reason."""
    ranked = Counter(counts).most_common()
    text = ", ".join(f"{reason} ×{n}" for reason, n in ranked)
    why = (first or {}).get(ranked[0][0], "") if ranked else ""
    return f"{text}; {why}" if why and not why.endswith(f": {ranked[0][0]}") else text


def wrote_before_stopping(written) -> str:
    """``wrote N frame(s) to A, B before stopping`` (``and M to C`` where an output holds another
    count): what a run that ends early leaves behind, from (frames, path) pairs."""
    paths: dict[int, list] = {}
    for frames, path in written:
        paths.setdefault(frames, []).append(str(path))
    parts = [f"{counted(n, 'frame') if k == 0 else n} to {', '.join(p)}" for k, (n, p) in enumerate(paths.items())]
    return f"wrote {' and '.join(parts)} before stopping"


def _resolved(option: str, path: Path) -> Path:
    """``path`` with its links followed; a UsageError for links that lead back to themselves
    (``Path.resolve`` raises on them before Python 3.13, and returns them unresolved since)."""
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise click.UsageError(f"{option} {path}: a symbolic link that leads back to itself") from None
    except ValueError:  # a NUL in the name: said where the path is checked for writing
        pass
    return Path(path).resolve()


def check_outputs(outputs: dict[str, Path | None], inputs: Iterable[str | Path | None]) -> None:
    """Raise a UsageError when an output (option name → path) is an input file (also through a
    link) or lies inside an input folder, or when two outputs are one file: a report must never
    replace the data it reports on, nor another report. A rosbag2's metadata.yaml stands for its
    folder, as for the sources. Then :class:`Failed` where an output cannot be written
    (:func:`writable`; probed only once it is known not to touch an input folder)."""
    from terrainmap.sources import log_path

    given = {option: _resolved(option, path) for option, path in outputs.items() if path is not None}
    for (a, path), (b, other) in itertools.combinations(given.items(), 2):
        if path == other:
            raise click.UsageError(f"{a} and {b} are the same file {outputs[a]}")
    for option, path in outputs.items():
        if path is None:
            continue
        target = given[option]
        for source in (log_path(p) for p in inputs if p is not None):
            same = target.exists() and source.exists() and os.path.samefile(target, source)
            if same or target == source.resolve():
                raise click.UsageError(f"{option} {path} would overwrite the input {source}")
            if source.is_dir() and source.resolve() in target.parents:
                raise click.UsageError(f"{option} {path} lies inside the input folder {source}; write it elsewhere")
    for path in outputs.values():
        if path is not None:
            writable(Path(path))


def write_text(path: Path, text: str) -> None:
    """Write an output file whole or not at all (through a temporary file beside it); a failure
    (disk full, permissions) is one line naming the file."""
    with writing(path) as partial:
        partial.write_text(text)


@contextmanager
def writing(path) -> Iterator[Path]:
    """A temporary path beside ``path``, with its suffix, for a library call to write (a plot);
    renamed to ``path`` once written whole (to the file it links to, where ``path`` is a symbolic
    link, which stays), and said so on stdout. An OSError (disk full) becomes one line naming
    ``path``, which is left as it was; on any failure (an interrupt too) the temporary file goes."""
    path = Path(path)
    target = Path(os.path.realpath(path))
    partial = target.with_name(f".{target.stem}.partial{target.suffix}")
    try:
        yield partial
        partial.replace(target)
    except BaseException as exc:
        partial.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise Failed(f"cannot write {path}: {exc.strerror or exc}") from exc
        raise
    click.echo(f"wrote {path}")


def writable(path: Path) -> None:
    """Raise :class:`Failed` naming ``path`` when it cannot be written, without changing it: an
    existing file is opened for appending, a folder gets a temporary file that goes at once, a new
    file is created and removed again; anything else there (a FIFO would block, a device...) is
    refused."""
    target = Path(os.path.realpath(path))  # a symbolic link stays, even one to a file not yet there
    existed = target.exists()
    if existed and not (target.is_file() or target.is_dir()):
        raise Failed(f"{path} exists and is neither a regular file nor a folder")
    try:
        if target.is_dir():
            tempfile.TemporaryFile(dir=target).close()
        else:
            with open(target, "ab"):
                pass
    except OSError as exc:
        raise Failed(f"cannot write {path}: {exc.strerror or exc}") from None
    if not existed:
        target.unlink(missing_ok=True)


def output_file(*suffixes: str) -> Callable:
    """A click callback for an output file option: its folder must exist and, where ``suffixes``
    are given, its name must end in one of them (click's ``dir_okay`` decides whether it may be a
    folder; a report's suffix keeps a log named by a slip from being replaced by it). Gives a Path;
    the command then checks it against its inputs and that it can be written, before any work
    (:func:`check_outputs`)."""

    def check(ctx: click.Context, param: click.Parameter, value) -> Path | None:
        if value is None:
            return None
        if not str(value).strip():
            raise click.BadParameter("must name a file, got an empty path")
        path = Path(value)
        if not path.parent.is_dir():
            what = f"{path.parent} is not a folder" if path.parent.exists() else f"folder {path.parent} does not exist"
            raise click.BadParameter(what)
        if suffixes and path.suffix.lower() not in suffixes:
            raise click.BadParameter(f"{path} must end in {', '.join(suffixes)}")
        return path

    return check


def config_options(func: Callable) -> Callable:
    """``--config PATH.toml`` and repeatable ``--set section.field=value``."""
    func = click.option(
        "--set",
        "overrides",
        multiple=True,
        metavar="SECTION.FIELD=VALUE",
        help="Override one config field, e.g. --set terrain.control_points_x=15 (repeatable).",
    )(func)
    return click.option(
        "--config", "config_path", type=click.Path(dir_okay=False), multiple=True, callback=_one_config,
        help="TOML config file.",
    )(func)


def _one_config(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> str | None:
    """The ``--config`` file, refusing a second one (click would keep the last silently)."""
    if len(values) > 1:
        raise click.BadParameter(f"given {len(values)} times; give one file, and --set for single fields")
    return values[0] if values else None
