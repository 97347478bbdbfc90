"""Heavy stages in a child process, so that Ctrl-C and SIGTERM stop any of them within a second.

pycolmap's C++ calls look at signals rarely or never: feature extraction and matching every 2 s and only in
the main thread, the incremental mapper only when an image registers (never during its initial-pair search),
the global mapper never, and ``BundleAdjuster.solve`` keeps the GIL, so not even a Python thread can run until
it returns. A signal handler in the process that runs them may therefore wait for minutes.

:func:`in_child` runs one stage function in a child process and only waits for it: the caller's signal
handlers (``KeyboardInterrupt``, the CLI's ``Terminated``) run within ``POLL_S``, and whatever exception leaves
the wait kills the child (SIGKILL) before it propagates. Every stage writes its results atomically (SQLite
transactions, :func:`rigsfm.core.io.atomic_directory`), so a killed stage loses only its own unfinished work;
the temporary folders it leaves are swept by :meth:`rigsfm.core.workspace.Workspace.prepare`.

- Children fork from a forkserver (a fresh interpreter, started once, with the modules named in
  :func:`start` imported): a stage starts in milliseconds and never inherits locks of the caller's threads.
- Arguments and results travel by pickle; ``pycolmap.Reconstruction`` (which does not pickle) as its binary
  model files. Callable arguments (progress callbacks) are replaced by proxies that forward each call to the
  caller, which makes it there (the call returns None in the child).
- The child's log records are handled by the caller's loggers; COLMAP's own log (glog, on fd 2) and prints go
  to the caller's fd 2 and fd 1 as they are at the call (e.g. ``OUT/colmap.log``).
- The child ignores SIGINT (a terminal's Ctrl-C reaches the whole process group: the caller decides) and dies
  with its parent.

``RIGSFM_IN_PROCESS=1`` (or :func:`in_process`) runs stages in the calling process instead, e.g. for a debugger.
"""

from __future__ import annotations

import contextlib
import copyreg
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import resource
import signal
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable, Iterable, Iterator
from multiprocessing import reduction
from pathlib import Path
from typing import TypeVar

import pycolmap

from rigsfm.core.errors import RigsfmError

logger = logging.getLogger(__name__)

POLL_S = 0.1  # the longest the caller waits without running its signal handlers
IN_PROCESS_ENV = "RIGSFM_IN_PROCESS"

T = TypeVar("T")


class StageDied(RigsfmError):
    """A stage's process ended without a result (killed by the system, e.g. out of memory)."""


# --- pycolmap.Reconstruction by pickle -----------------------------------------------------------------------


def _reconstruction_from_files(files: dict[str, bytes]) -> pycolmap.Reconstruction:
    with tempfile.TemporaryDirectory(prefix="rigsfm-model-") as folder:
        for name, data in files.items():
            Path(folder, name).write_bytes(data)
        return pycolmap.Reconstruction(folder)


def _reduce_reconstruction(reconstruction: pycolmap.Reconstruction):
    with tempfile.TemporaryDirectory(prefix="rigsfm-model-") as folder:
        reconstruction.write_binary(folder)
        files = {path.name: path.read_bytes() for path in Path(folder).iterdir()}
    return _reconstruction_from_files, (files,)


copyreg.pickle(pycolmap.Reconstruction, _reduce_reconstruction)


# --- the forkserver ------------------------------------------------------------------------------------------

# rigsfm.core._forkserver right after pycolmap: it undoes glog's SIGTERM handler and lets the signals through, so
# that a signal during the other (slow) imports ends the server at once.
_PRELOAD = ["pycolmap", "rigsfm.core._forkserver", __name__]
_context: multiprocessing.context.ForkServerContext | None = None


def start(preload: Iterable[str] = ()) -> None:
    """Start the forkserver now, importing ``preload`` (the stage functions' modules) once, there, while the
    caller goes on; otherwise it starts at the first stage. Modules named after it has started are imported by
    each child instead (slower, same result)."""
    global _context
    if not runs_in_child():
        return
    if _context is None:
        _context = multiprocessing.get_context("forkserver")
    _PRELOAD.extend(name for name in preload if name not in _PRELOAD)
    _context.set_forkserver_preload(_PRELOAD)
    from multiprocessing import forkserver, resource_tracker

    resource_tracker.ensure_running()  # first: starting it unblocks SIGINT and SIGTERM in this thread
    # The server starts with SIGINT and SIGTERM blocked (a new process inherits the mask), so a signal during its
    # imports neither prints a traceback (SIGINT, before multiprocessing ignores it there) nor glog's stack
    # (SIGTERM, once pycolmap is imported); rigsfm.core._forkserver unblocks them when its handlers are set.
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, (signal.SIGINT, signal.SIGTERM))
    try:
        forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def stop() -> None:
    """End the forkserver now (its stage processes die with it): a stopped command need not wait for it to
    finish its imports, which would hold the command's output pipes open for seconds."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    if pid is not None:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)


# --- the child -----------------------------------------------------------------------------------------------


class _Fd:
    """One of the caller's file descriptors, handed to the child through the forkserver (like a fork's)."""

    def __init__(self, fd: int):
        self.fd = fd

    def __reduce__(self):
        return _Fd._received, (reduction.DupFd(self.fd),)

    @staticmethod
    def _received(dup) -> int:
        return dup.detach()


def _send(conn, message) -> None:
    """Send to the caller; if it is gone (stopped, so it closed its end), end quietly: nobody waits."""
    try:
        conn.send(message)
    except OSError:
        os._exit(1)


class _Forward:
    """Stands in for a callable argument in the child: each call is made by the caller."""

    def __init__(self, conn, key):
        self.conn, self.key = conn, key

    def __call__(self, *args, **kwargs) -> None:
        _send(self.conn, ("call", self.key, args, kwargs))


class _ForwardLog(logging.Handler):
    def __init__(self, conn):
        super().__init__()
        self.conn = conn

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        record.msg, record.args, record.exc_info = record.getMessage(), None, None
        _send(self.conn, ("log", record))


def _die_with_parent() -> None:
    """The forkserver exits when the caller does; make sure this child follows (PR_SET_PDEATHSIG on Linux,
    which works even while a C++ call holds the GIL; a watching thread elsewhere)."""
    parent = os.getppid()
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, signal.SIGKILL, 0, 0, 0) != 0:  # PR_SET_PDEATHSIG
            raise OSError(ctypes.get_errno(), "prctl")
        if os.getppid() != parent:
            os._exit(70)
        return
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent:
            threading.Event().wait(0.5)
        os._exit(70)

    threading.Thread(target=watch, daemon=True).start()


def _child(conn, fn, args, kwargs, callables, stdout: int, stderr: int, log_level: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not glog's handler (a C stack), nor the caller's
    _die_with_parent()
    try:  # the caller's go-ahead: it stopped before it could track this child if it never comes
        if conn.recv() != "go":
            os._exit(1)
    except (EOFError, OSError):
        os._exit(1)
    for fd, target in ((stdout, 1), (stderr, 2)):
        os.dup2(fd, target)
        os.close(fd)
    root = logging.getLogger()
    root.handlers[:] = [_ForwardLog(conn)]
    root.setLevel(log_level)
    args = list(args)
    for key in callables:
        if isinstance(key, int):
            args[key] = _Forward(conn, key)
        else:
            kwargs[key] = _Forward(conn, key)
    try:
        result = fn(*args, **kwargs)
        _send(conn, ("cpu", cpu_seconds(), peak_rss_mb()))
    except BaseException as error:  # noqa: BLE001 - every failure goes back to the caller
        text = traceback.format_exc()
        try:
            pickle.loads(pickle.dumps(error))
        except Exception:  # an exception that does not pickle, or not back
            error = RuntimeError(f"{type(error).__name__}: {error}")
        _send(conn, ("error", error, text))
    else:
        _send(conn, ("result", result))
    finally:
        conn.close()


# --- the caller ----------------------------------------------------------------------------------------------

_in_process = threading.local()
_children_cpu = [0.0]  # CPU seconds of the stage processes that finished with a result
_children_peak_mb = [0.0]  # the largest peak resident memory of those processes


def cpu_seconds() -> float:
    """CPU seconds (every thread) of this process."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def stage_cpu_seconds() -> float:
    """CPU seconds of this process plus those of every stage process that finished here so far."""
    return cpu_seconds() + _children_cpu[0]


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB, C++ allocations included): Linux's VmHWM (a stage process's
    starts at the forkserver's resident size, the modules it preloaded), else ``ru_maxrss``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def stage_peak_rss_mb() -> float:
    """The peak resident memory (MB) of this process or of any stage process that finished here so far,
    whichever is larger (a run's peak: the stages run one at a time)."""
    return max(peak_rss_mb(), _children_peak_mb[0])


@contextlib.contextmanager
def in_process() -> Iterator[None]:
    """Run stages in this process within the block (what ``RIGSFM_IN_PROCESS=1`` does everywhere)."""
    saved = getattr(_in_process, "on", False)
    _in_process.on = True
    try:
        yield
    finally:
        _in_process.on = saved


def runs_in_child() -> bool:
    return not (getattr(_in_process, "on", False) or os.environ.get(IN_PROCESS_ENV) == "1")


def _threshold() -> int:
    """The lowest level any of the caller's loggers with a handler keeps (the child forwards only those)."""
    levels = [logging.getLogger().getEffectiveLevel()]
    for item in logging.Logger.manager.loggerDict.values():
        if isinstance(item, logging.Logger) and item.handlers:
            levels.append(item.getEffectiveLevel())
            levels.extend(handler.level for handler in item.handlers if handler.level)
    return min(levels)


@contextlib.contextmanager
def _main_not_imported() -> Iterator[None]:
    """Start a child without running the caller's ``__main__`` again there (multiprocessing would, as
    ``__mp_main__``: a script calling ``rigsfm.run`` at top level, without ``if __name__ == "__main__"``, would
    run again in every stage). Stages never need it: their functions and arguments live in importable
    modules, and callables are proxied."""
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved: dict[str, object] = {name: main.__dict__[name] for name in ("__file__", "__spec__") if name in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)


def _stage_name(fn: Callable) -> str:
    return getattr(fn, "__qualname__", repr(fn))


def in_child(fn: Callable[..., T], *args, **kwargs) -> T:
    """``fn(*args, **kwargs)`` in a child process; returns its result or raises its exception.

    ``fn`` must be importable by name (a module-level function). Any exception in the caller while it waits
    (``KeyboardInterrupt`` from Ctrl-C, the CLI's ``Terminated`` on SIGTERM) kills the child first.
    """
    if not runs_in_child():
        return fn(*args, **kwargs)
    if _context is None:
        start()
    assert _context is not None, "runs_in_child() changed meanwhile"
    callables = {key: value for key, value in [*enumerate(args), *kwargs.items()]
                 if callable(value) and not isinstance(value, type)}
    plain_args = tuple(None if i in callables else value for i, value in enumerate(args))
    plain_kwargs = {key: value for key, value in kwargs.items() if key not in callables}
    receiver, sender = _context.Pipe(duplex=True)
    process = _context.Process(
        target=_child, name=f"rigsfm {_stage_name(fn)}", daemon=True,
        args=(sender, fn, plain_args, plain_kwargs, tuple(callables), _Fd(1), _Fd(2), _threshold()))
    try:
        with _main_not_imported():
            process.start()
        sender.close()
        receiver.send("go")  # stopped before this, the caller cannot kill the child: it ends by itself
        while True:
            ready = multiprocessing.connection.wait([receiver, process.sentinel], timeout=POLL_S)
            if receiver in ready:
                try:
                    message = receiver.recv()
                except EOFError:  # the child closed its end without a result
                    message = ("died",)
            elif process.sentinel in ready:
                message = ("died",)
            else:
                continue
            kind = message[0]
            if kind == "call":
                callables[message[1]](*message[2], **message[3])
            elif kind == "log":
                record = message[1]
                target = logging.getLogger(record.name)
                if target.isEnabledFor(record.levelno):
                    target.handle(record)
            elif kind == "cpu":
                _children_cpu[0] += message[1]
                _children_peak_mb[0] = max(_children_peak_mb[0], message[2])
            elif kind == "result":
                return message[1]
            elif kind == "error":
                _, error, text = message
                error.add_note(f"(raised in the stage process)\n{text}")
                raise error
            else:
                process.join()
                code = process.exitcode
                how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
                raise StageDied(f"the {_stage_name(fn)} stage stopped without a result ({how}; out of memory?); re-run "
                                "the same command to resume, with fewer threads or smaller images if it happens again")
    finally:
        sender.close()
        if process.pid is not None:
            if process.is_alive():
                process.kill()
            process.join()
        receiver.close()

