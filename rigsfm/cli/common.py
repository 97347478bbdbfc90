"""What every command shares: one red line per error, signals, logging, progress bars, option helpers.

Exit codes: 0 done, 1 an error the user can fix, 2 a usage error (typer), 3 an internal error (traceback in
a file), 4 finished with warnings under ``--strict``, 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import sys
import tempfile
import traceback

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn
from rich.text import Text

from rigsfm.cli import _signals
from rigsfm.cli._signals import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated  # noqa: F401  (re-exported)


class _Console(Console):
    """Plain text, never Rich markup: messages hold user names and paths (``frame[cam].png``, ``[/]``) that
    markup would eat or choke on; styles come from :func:`styled`. Output that is not a terminal keeps each
    line whole (no wrapping at an assumed 80 columns), so scripts and logs can grep it."""

    def __init__(self, **kwargs):
        super().__init__(markup=False, highlight=False, **kwargs)

    @property
    def soft_wrap(self) -> bool:  # looked up at each print: the stream may be swapped (tests, redirection)
        return not self.is_terminal

    @soft_wrap.setter
    def soft_wrap(self, value: bool) -> None:
        pass


console = _Console()
err_console = _Console(stderr=True)

EXIT_ERROR, EXIT_INTERNAL, EXIT_WARNINGS = 1, 3, 4


def styled(head: str, style: str, rest: str) -> Text:
    """``head`` in ``style``, then ``rest`` verbatim."""
    return Text.assemble((head, style), " ", rest)


def flag(*names: str, help: str) -> typer.models.OptionInfo:
    """A boolean option shown as a plain flag (``--overwrite``), not ``--overwrite <bool>``."""
    return typer.Option(*names, help=help, metavar="")


def say_error(message: str) -> None:
    err_console.print(styled("error:", "bold red", message), soft_wrap=True)  # one line, however long


def say_stopped(signum: int) -> None:
    head, rest = _signals.message(signum)
    err_console.print(styled(head, "bold red", rest), soft_wrap=True)


def fail_cleanly(command):
    """Run a command: every ``RigsfmError`` and OS error becomes one red line and exit code 1, Ctrl-C and SIGTERM
    one line (the work is resumable), anything else one line with the traceback in a file (exit code 3)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from rigsfm.core.errors import RigsfmError
        from rigsfm.core.workspace import os_error_text

        try:
            with _signals.raising():
                _signals.import_native()
                return command(*args, **kwargs)
        except typer.Exit:
            raise
        except BaseException as error:
            # After a signal, whatever comes out is the stop: a library may have wrapped the KeyboardInterrupt
            # (ImportError, RuntimeError) or failed because of it.
            signum = _signals.received()
            if signum is None and isinstance(error, (KeyboardInterrupt, Terminated)):
                signum = signal.SIGINT if isinstance(error, KeyboardInterrupt) else signal.SIGTERM
            if signum is not None:
                if "rigsfm.core.processes" in sys.modules:
                    sys.modules["rigsfm.core.processes"].stop()
                _signals.forget_unhandled_interrupt()
                say_stopped(signum)
                raise typer.Exit(_signals.exit_code(signum)) from None
            if isinstance(error, RigsfmError):
                say_error(str(error))
                raise typer.Exit(EXIT_ERROR) from None
            if isinstance(error, OSError):  # disk full, read-only, permission: the user's to fix, with the path
                from rigsfm.core.io import real_path

                where = f"{real_path(error.filename)}: " if error.filename else ""
                say_error(f"{where}{os_error_text(error)}; {os_error_advice(error)}")
                raise typer.Exit(EXIT_ERROR) from None
            if not isinstance(error, Exception):  # SystemExit and the like: not ours to reword
                raise
            # A bug, not the user's input: one line, the traceback in a file.
            with tempfile.NamedTemporaryFile("w", prefix="rigsfm-error-", suffix=".txt", delete=False) as f:
                traceback.print_exc(file=f)
            err_console.print(styled("internal error:", "bold red", f"{type(error).__name__}: {error} "
                                     f"(traceback in {f.name}; please report it)"), soft_wrap=True)
            raise typer.Exit(EXIT_INTERNAL) from None
        finally:
            _signals.hold_back()

    return wrapper


def os_error_advice(error: OSError) -> str:
    import errno

    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return "free space, then re-run the same command (finished work is kept)"
    if error.errno == errno.EROFS:
        return "choose a folder you can write to"
    if error.errno in (errno.EACCES, errno.EPERM):
        return "check its permissions, or choose a folder you can write to"
    if isinstance(error, ConnectionError):
        return "check the address and that the other side is running"
    return "check the path"


def configure_logging(verbose: bool) -> None:
    """rigsfm's own log on the terminal (warnings, or everything with -v); COLMAP's goes to OUT/colmap.log."""
    from rich.logging import RichHandler

    level = logging.INFO if verbose else logging.WARNING
    console = _log_console()
    handler: logging.Handler
    if console.is_terminal:
        handler = RichHandler(console=console, level=level, show_path=False, show_time=False)
        # basicConfig gives a handler without a formatter its BASIC_FORMAT ('WARNING:name:...'), which RichHandler
        # would print after its own level column
        handler.setFormatter(logging.Formatter("%(message)s"))
    else:  # one whole line per record where it is read by a program or a file
        handler = _ConsoleStreamHandler(console)
        handler.setLevel(level)
        handler.setFormatter(logging.Formatter("%(levelname)-8s %(message)s"))  # as RichHandler shows it
    logging.basicConfig(level=logging.INFO, handlers=[handler], force=True)


class _ConsoleStreamHandler(logging.StreamHandler):
    """Writes to the console's stream as it is at each record, not as it was when logging was configured: an
    in-process caller (a test, a notebook) may close and replace ``sys.stderr`` after the command returns."""

    def __init__(self, console: Console):
        self._console = console
        super().__init__()

    @property
    def stream(self):  # type: ignore[override]
        return self._console.file

    @stream.setter
    def stream(self, value) -> None:
        pass


_LOG_CONSOLE: list[Console] = []


def _log_console() -> Console:
    """Where rigsfm's log reaches the terminal: a console on a copy of the process's stderr (file descriptor 2),
    which ``colmap_log_to`` points at OUT/colmap.log while the stages run (their warnings are for the user);
    ``err_console`` when stderr is no file descriptor (a test's captured output)."""
    try:
        if sys.stderr.fileno() != 2:
            return err_console
    except (AttributeError, OSError, ValueError):
        return err_console
    if not _LOG_CONSOLE:
        _LOG_CONSOLE.append(Console(file=os.fdopen(os.dup(2), "w", buffering=1), stderr=True))
    return _LOG_CONSOLE[0]


class _FirstWorkProgress(Progress):
    """Progress bars shown from the first report of work on: an error before any (a wrong path, a refused input)
    is the command's only output, not an empty display left above it (a blank line where stdout is piped)."""

    def __enter__(self) -> _FirstWorkProgress:
        return self

    def update(self, task_id: TaskID, **kwargs) -> None:  # type: ignore[override]
        if not self.live.is_started:
            self.start()
        super().update(task_id, **kwargs)

    def stop(self) -> None:
        if self.live.is_started:  # rich's own stop ends a display never shown with a blank line where not a terminal
            super().stop()


def progress_bars() -> Progress:
    return _FirstWorkProgress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(),
                              TimeElapsedColumn(), console=console, transient=False)


class StageProgress:
    """A rich progress bar per pipeline stage, created on the stage's first report."""

    def __init__(self, progress: Progress):
        self.progress = progress
        self.tasks: dict[str, TaskID] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        total_or_unknown = total or None  # (stage, 0, 0): the stage started, its total comes later
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total_or_unknown)
        if total_or_unknown is None:
            self.progress.update(self.tasks[stage], completed=done)
        else:
            self.progress.update(self.tasks[stage], completed=done, total=total)


def finish(warnings: list[str], strict: bool) -> None:
    """Print the warnings; under ``--strict`` any warning makes the exit code non-zero (4)."""
    for warning in warnings:
        console.print(styled("warning:", "bold yellow", warning), soft_wrap=True)
    if strict and warnings:
        err_console.print(styled(f"{len(warnings)} warning(s)", "bold red", f"and --strict: exit code {EXIT_WARNINGS}"))
        raise typer.Exit(EXIT_WARNINGS)

