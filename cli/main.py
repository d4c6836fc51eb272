"""Entry point: the ``terrainmap`` click group.

Commands live in their own modules and are imported only when used, so ``terrainmap --help``
stays fast. Library errors (:class:`terrainmap.errors.TerrainmapError`) become one-line
messages and exit code 2; ``--verbose`` shows the traceback instead.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import signal
import sys
import threading
import traceback
from contextlib import contextmanager, suppress

import click

# first terrainmap import: limits OpenBLAS's threads
from terrainmap.errors import ConfigError, TerrainmapError

from .options import GracefulStop, leave_hung_up_terminal, point_at_null_device, take_stop_signals

# command name -> "module:attribute" (modules relative to terrainmap.cli)
COMMANDS = {
    "bench": "bench_cmd:bench",
    "config": "config_cmd:config",
    "eval": "eval_cmd:eval_group",
    "info": "info_cmd:info",
    "process": "process_cmd:process",
    "simulate": "simulate_cmd:simulate",
}


class _Interrupted(Exception):
    """A KeyboardInterrupt (Ctrl-C, or SIGTERM made one) carried past click, whose own handler
    prints an empty line before its Abort: :func:`main` says "Interrupted." alone."""


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def __init__(self, *args, lazy: dict[str, str], **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy = lazy

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(self.lazy))

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:
            raise _Interrupted from exc

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in self.lazy:
            module, attr = self.lazy[name].split(":")
            return getattr(importlib.import_module(f"terrainmap.cli.{module}"), attr)
        return super().get_command(ctx, name)


@click.group(cls=LazyGroup, lazy=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="Log progress details and show tracebacks on errors.")
@click.version_option(package_name="terrainmap")
@click.pass_context
def cli(ctx: click.Context, verbose: bool) -> None:
    """terrainmap: terrain maps from stereo camera logs (Broggi et al., rational B-splines)."""
    ctx.ensure_object(dict)["verbose"] = verbose  # main() passes the dict in: it outlives the context
    if not verbose:  # OpenCV's and Rerun's own log lines (e.g. "[ERROR] ... IHDR" on a corrupt PNG, Rerun's
        os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")  # on a full disk) would add to the one-line
        os.environ.setdefault("RUST_LOG", "off")  # error; both read at their import
    # Warnings as one line each ("warning: <file>: ..."); with -v, the module that logged it too.
    fmt = "%(levelname)s %(name)s: %(message)s" if verbose else "warning: %(message)s"
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format=fmt)


def _signal_exit_code() -> int:
    """128 + the signal that stopped the run: 130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP, 152 for SIGXCPU."""
    return 128 + (GracefulStop.last_signal or signal.SIGINT)


@contextmanager
def _terminate_as_interrupt():
    """While the CLI runs, SIGTERM, SIGHUP and SIGXCPU end it as Ctrl-C does ("Interrupted.", exit
    code 143, 129 or 152) instead of killing it silently: commands whose outputs are written whole or not at all
    (``eval``, ``bench``) clean up their partial files on the way out. Runs that write as they go
    (``process``, ``simulate``) take the signals over with :class:`GracefulStop` meanwhile. A signal
    the process was started ignoring stays ignored; off the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        GracefulStop.last_signal = signum  # kept: a destructor the signal lands in swallows the interrupt
        leave_hung_up_terminal(signum)
        raise KeyboardInterrupt

    previous = take_stop_signals(interrupt)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _exit_at_once(signum, frame) -> None:
    """A signal after the command has ended: its outputs are all closed; end with the interrupted
    run's exit code now, not with a traceback from an exit handler."""
    leave_hung_up_terminal(signum)
    _end_now(128 + signum, "Interrupted.")


def _end_now(code: int, message: str = "") -> None:
    """End the process at once (``os._exit``), after flushing standard output and error and
    writing ``message`` as a line to the latter (a failing stream changes nothing by then)."""
    with suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
        if message:  # (not through sys.stderr: the signal handler that calls this may have cut a write to it)
            os.write(2, f"{message}\n".encode())
    os._exit(code)


def main(argv: list[str] | None = None) -> None:
    """Run the CLI, turning library errors into one-line messages (exit code 2; with
    ``--verbose``, the traceback and exit code 2)."""
    GracefulStop.last_signal = None
    options: dict = {}  # the group's --verbose, as parsed (a file named -v is no flag)
    _open_closed_standard_streams()
    try:
        if "_TERRAINMAP_COMPLETE" not in os.environ:  # (tab completion uses no OpenCV)
            _check_opencv_environment()
        with _terminate_as_interrupt():
            cli.main(args=argv, prog_name="terrainmap", standalone_mode=False, obj=options)
        if GracefulStop.last_signal is not None:  # a signal whose interrupt a destructor swallowed
            raise KeyboardInterrupt
    except click.exceptions.Abort:  # click's form of a KeyboardInterrupt outside a run's GracefulStop
        click.echo("Interrupted.", err=True)
        sys.exit(_signal_exit_code())
    except _NO_ARGS_IS_HELP as exc:  # a bare command (group): its help, as click shows it
        exc.show()
        sys.exit(exc.exit_code)
    except click.UsageError as exc:  # one line, with the help hint click would print above it
        hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
        if isinstance(exc, click.NoSuchOption) and exc.option_name in ("-v", "--verbose"):
            hint = f" ({exc.option_name} goes before the command: terrainmap {exc.option_name} COMMAND ...)"
        click.echo(f"Error: {exc.format_message()}{hint}", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except TerrainmapError as exc:
        if options.get("verbose") and not isinstance(exc, ConfigError):  # (a bad option or setting: one line)
            traceback.print_exc()
        else:
            click.echo(f"Error: {exc}", err=True)
        _exit(2)
    except (KeyboardInterrupt, _Interrupted):
        if GracefulStop.last_signal in (None, signal.SIGINT) and sys.stderr.isatty():
            click.echo(err=True)  # past the terminal's "^C"
        click.echo("Interrupted.", err=True)
        sys.exit(_signal_exit_code())
    except MemoryError as exc:  # settings past what the machine holds (a huge grid or net)
        if options.get("verbose"):
            traceback.print_exc()
        click.echo(f"Error: out of memory{f' ({exc})' if str(exc) else ''}; a smaller grid, terrain net or image "
                   "may fit", err=True)
        sys.exit(2)
    except OSError as exc:  # a report or plot that cannot be written (disk full, permissions)
        if options.get("verbose"):
            traceback.print_exc()
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"Error: {where}{exc.strerror or exc}", err=True)
        sys.exit(2)


def _open_closed_standard_streams() -> None:
    """Point the standard streams closed when the process started (`2>&-`: Python's ``sys.stderr``
    is None) at the null device: their messages go nowhere, and a file opened later does not take
    their descriptor (where a message to standard error would then land)."""
    for fd in (0, 1, 2):  # in order: each closed one is the lowest free descriptor when it is opened
        try:
            os.fstat(fd)
        except OSError:
            point_at_null_device(fd)
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))  # noqa: SIM115 (the process's stream to its end)


_OPENCV_NUMBERS = ("OPENCV_FOR_THREADS_NUM", "OPENCV_IO_MAX_IMAGE_PIXELS", "OPENCV_IO_MAX_IMAGE_WIDTH",
                   "OPENCV_IO_MAX_IMAGE_HEIGHT")
"""OpenCV's environment settings that it parses as unsigned numbers: anything else ends in an
OpenCV exception mid-run, or aborts the process."""


def _check_opencv_environment() -> None:
    """:class:`ConfigError` for an :data:`_OPENCV_NUMBERS` setting OpenCV cannot read: a whole number
    below 2⁶⁴, optionally followed by KB or MB (any case but kB/mB), as OpenCV parses it."""
    for name in _OPENCV_NUMBERS:
        value = os.environ.get(name)
        number = re.fullmatch("([0-9]+)(?:[Kk]b|KB|[Mm]b|MB)?", value or "")
        if value is not None and not (number and int(number[1]) < 2**64):
            raise ConfigError(f"environment variable {name} must be a whole number, or one with KB or MB after it "
                              f"(OpenCV reads it), got {value!r}")


_NO_ARGS_IS_HELP = getattr(click.exceptions, "NoArgsIsHelpError", ())
"""click ≥ 8.2's error for a group called without a command (older clicks print the help themselves)."""


def _rerun_stuck() -> bool:
    """Whether Rerun would keep the process from ending (:func:`terrainmap.sinks.rerun_recording.exit_would_hang`)."""
    rerun_sink = sys.modules.get("terrainmap.sinks.rerun_recording")
    return rerun_sink is not None and rerun_sink.exit_would_hang()


def _exit(code: int) -> None:
    """``sys.exit(code)``, or ``os._exit`` where Rerun would keep the process from ending."""
    if _rerun_stuck():
        _end_now(code)
    sys.exit(code)


def run() -> None:
    """The ``terrainmap`` console command: :func:`main`, then the process ends at once, its output
    streams flushed, with main's exit code. Every output is closed by then; the interpreter's own
    exit (0.2 s, 0.5 s after a Rerun recording, whose exit handler shuts its threads down) would
    only leave a window where a signal ends in a traceback and exit code 0, or kills the process
    without a word. Outside main's run, a signal ends the process with the interrupted run's code."""
    take_stop_signals(_exit_at_once)  # main takes them over while it runs, and gives these back
    code, message = 0, ""
    try:
        main()
    except SystemExit as exc:
        if isinstance(exc.code, int):
            code = exc.code
        elif exc.code is not None:  # sys.exit("message"): 1, the message printed as Python does
            code, message = 1, str(exc.code)
    _end_now(code, message)


if __name__ == "__main__":
    run()
