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
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

console = Console()
err_console = Console(stderr=True)

EXIT_ERROR, EXIT_INTERNAL, EXIT_WARNINGS, EXIT_INTERRUPTED, EXIT_TERMINATED = 1, 3, 4, 130, 143


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt so the same cleanup runs."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def _import_native_libraries() -> None:
    """pycolmap's import (glog's failure handler) takes SIGTERM over, printing a C stack trace and no message;
    imported before ``fail_cleanly`` sets its handler, it cannot (0.2 s, which most commands spend anyway)."""
    import pycolmap  # noqa: F401


def flag(*names: str, help: str) -> typer.models.OptionInfo:
    """A boolean option shown as a plain flag (``--overwrite``), not ``--overwrite <bool>``."""
    return typer.Option(*names, help=help, metavar="")


def say_error(message: str) -> None:
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)


def fail_cleanly(command):
    """Run a command: every ``RigsfmError`` and OS error becomes one red line and exit code 1, Ctrl-C and SIGTERM
    one line (the work is resumable), anything else one line with the traceback in a file (exit code 3)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from rigsfm.core.errors import RigsfmError
        from rigsfm.core.workspace import os_error_text

        _import_native_libraries()  # first: their import replaces the SIGTERM handler
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
        try:
            return command(*args, **kwargs)
        except RigsfmError as error:
            say_error(str(error))
            raise typer.Exit(EXIT_ERROR) from None
        except KeyboardInterrupt:
            err_console.print("[bold red]interrupted[/] (Ctrl-C): nothing finished was lost; re-run the same command "
                              "to resume", soft_wrap=True)
            raise typer.Exit(EXIT_INTERRUPTED) from None
        except Terminated:
            err_console.print("[bold red]terminated[/] (SIGTERM): nothing finished was lost; re-run the same command "
                              "to resume", soft_wrap=True)
            raise typer.Exit(EXIT_TERMINATED) from None
        except OSError as error:  # disk full, read-only, permission: the user's to fix, with the path
            where = f"{error.filename}: " if error.filename else ""
            say_error(f"{where}{os_error_text(error)}; {os_error_advice(error)}")
            raise typer.Exit(EXIT_ERROR) from None
        except typer.Exit:
            raise
        except Exception as error:  # a bug, not the user's input: one line, the traceback in a file
            with tempfile.NamedTemporaryFile("w", prefix="rigsfm-error-", suffix=".txt", delete=False) as f:
                traceback.print_exc(file=f)
            err_console.print(f"[bold red]internal error:[/] {type(error).__name__}: {error} "
                              f"(traceback in {f.name}; please report it)", highlight=False, soft_wrap=True)
            raise typer.Exit(EXIT_INTERNAL) from None
        finally:
            signal.signal(signal.SIGTERM, previous)

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

    handler = RichHandler(console=_log_console(), level=logging.INFO if verbose else logging.WARNING,
                          show_path=False, show_time=False)
    logging.basicConfig(level=logging.INFO, handlers=[handler], format="%(message)s", force=True)


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


def progress_bars() -> Progress:
    return Progress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    console=console, transient=False)


class StageProgress:
    """A rich progress bar per pipeline stage, created on the stage's first report."""

    def __init__(self, progress: Progress):
        self.progress = progress
        self.tasks: dict[str, int] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total)
        self.progress.update(self.tasks[stage], completed=done, total=total)


def finish(warnings: list[str], strict: bool) -> None:
    """Print the warnings; under ``--strict`` any warning makes the exit code non-zero (4)."""
    for warning in warnings:
        console.print(f"[bold yellow]warning:[/] {warning}", highlight=False, soft_wrap=True)
    if strict and warnings:
        err_console.print(f"[bold red]{len(warnings)} warning(s)[/] and --strict: exit code {EXIT_WARNINGS}")
        raise typer.Exit(EXIT_WARNINGS)

