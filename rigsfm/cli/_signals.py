"""SIGINT and SIGTERM for the ``rigsfm`` command, from its first instant to its exit.

Imported first by :mod:`rigsfm.cli` (standard library only, so it is in place within milliseconds). Until a
command's body runs (:func:`raising`) a signal ends the process at once with rigsfm's one line: nothing has
been written yet, and an exception raised inside a module's import is what native libraries turn into other
errors ("Cannot import the C++ backend"). While a command runs, SIGINT raises ``KeyboardInterrupt`` and
SIGTERM :class:`Terminated`, so its cleanup (killing stage processes) runs before the same line is printed; one
that lands where Python can only print an exception (a weakref callback, ``__del__``) is sent again.

pycolmap's import installs glog's failure handler over SIGTERM (a C stack trace, no message):
:func:`import_native` imports it with both signals blocked and puts our handler back before unblocking, so a
signal sent meanwhile is handled here, a moment later.
"""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import time
from collections.abc import Iterator

EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143
SIGNALS = (signal.SIGINT, signal.SIGTERM)
RESUME = "nothing finished was lost; re-run the same command (run and track go on from where they stopped)"


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt so the same cleanup runs."""


_state = {"raising": False, "received": None}
_installed: set[int] = set()
_ignored: set[int] = set()  # ignored by whoever started us: kept ignored (glog's import would take them)


def message(signum: int) -> tuple[str, str]:
    """The line's first words (shown in red) and the rest."""
    if signum == signal.SIGINT:
        return "interrupted", f"(Ctrl-C): {RESUME}"
    return "terminated", f"(SIGTERM): {RESUME}"


def exit_code(signum: int) -> int:
    return EXIT_INTERRUPTED if signum == signal.SIGINT else EXIT_TERMINATED


def received() -> int | None:
    """The signal that arrived while the command ran, if one did."""
    return _state["received"]


def _handler(signum, frame) -> None:
    _state["received"] = signum
    if _state["raising"]:
        raise KeyboardInterrupt() if signum == signal.SIGINT else Terminated()
    head, rest = message(signum)
    red = sys.stderr.isatty() and "NO_COLOR" not in os.environ
    line = f"\x1b[1;31m{head}\x1b[0m {rest}\n" if red else f"{head} {rest}\n"
    with contextlib.suppress(OSError):
        os.write(2, line.encode())
    os._exit(exit_code(signum))


def _unraisable(unraisable) -> None:
    """A signal's exception raised where Python can only print it ("Exception ignored in": a weakref callback such
    as the import system's module locks, a ``__del__``) is asked for again, so it is raised in the code that runs
    next instead of being lost with a traceback."""
    signum = _state["received"]
    if signum is not None and isinstance(unraisable.exc_value, (KeyboardInterrupt, Terminated)):
        # from another thread, a moment later: raised in this hook, the exception would be ignored again
        _thread.start_new_thread(_send_again, (signum,))
        return
    _previous_unraisablehook(unraisable)


def _send_again(signum: int) -> None:
    time.sleep(0.01)
    os.kill(os.getpid(), signum)


_previous_unraisablehook = sys.unraisablehook


def is_the_command() -> bool:
    """Whether this process is the ``rigsfm`` command (its script, or ``python -m rigsfm``), not a program that
    imported the CLI (a test calling ``app`` in process keeps its own handlers)."""
    argv0 = os.path.basename(sys.argv[0]) if sys.argv else ""
    parent = os.path.basename(os.path.dirname(sys.argv[0])) if sys.argv else ""
    return argv0 == "rigsfm" or (argv0 == "__main__.py" and parent == "rigsfm")


def install() -> None:
    """Our handler for SIGINT and SIGTERM, except where the caller ignores one (a shell's background job
    ignores SIGINT, ``nohup``-like launchers SIGTERM): that choice is kept, as Python itself keeps it."""
    for signum in SIGNALS:
        if signum not in _installed and signal.getsignal(signum) is signal.SIG_IGN:
            _ignored.add(signum)
        signal.signal(signum, signal.SIG_IGN if signum in _ignored else _handler)
        _installed.add(signum)
    sys.unraisablehook = _unraisable
    # a mask inherited from the parent (a process that had them blocked while it started us) would hold them forever
    signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)


@contextlib.contextmanager
def blocked() -> Iterator[None]:
    """SIGINT and SIGTERM held back in the block (threads started in it keep them blocked, so the main thread
    gets them), our handlers reinstalled before they are let through."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    try:
        yield
    finally:
        if _installed:
            install()
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def import_native() -> None:
    """Import pycolmap (glog's handlers) without losing SIGTERM to it."""
    if "pycolmap" in sys.modules:
        return
    with blocked():
        import pycolmap  # noqa: F401


def hold_back() -> None:
    """The command is over (its result or its message is out): a signal from now on would only replace its exit
    code (Python's finalisation restores the default actions first), so the command's process ignores them."""
    if _installed:
        signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)


def handled() -> None:
    """The command took the signal as its normal end (``pick``'s Ctrl-C): what it raises next is its own outcome,
    not the stop."""
    _state["received"] = None


def forget_unhandled_interrupt() -> None:
    """Python exits by killing itself with SIGINT (exit status -2, not 130) when a KeyboardInterrupt once left code
    run through ``PyRun_String`` (native libraries' embedded Python), even if it was caught later; running any
    such code clears that mark."""
    import ctypes

    with contextlib.suppress(Exception):
        ctypes.pythonapi.PyRun_SimpleString(b"")


@contextlib.contextmanager
def raising() -> Iterator[None]:
    """Within the block a signal raises (``KeyboardInterrupt`` / :class:`Terminated`) instead of exiting."""
    _state["raising"] = True
    try:
        yield
    finally:
        _state["raising"] = False
