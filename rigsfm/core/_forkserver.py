"""Imported last by the forkserver of :mod:`rigsfm.core.processes`, only there.

pycolmap's import installs glog's failure handler for SIGTERM, which prints a C stack trace; a forkserver
terminated with its process group (systemd, Slurm) should just end, as it would without pycolmap. It was started
with SIGINT and SIGTERM blocked (:func:`rigsfm.core.processes.start`): they are let through here, SIGTERM ending
it quietly and SIGINT ignored (a terminal's Ctrl-C reaches the whole group: the caller decides).

A child forked here first reads its work from the caller. When the caller is stopped by a signal in the middle of
``Process.start`` (it printed its one line and left), the child finds the pipe closed (``EOFError``) or the work
cut off mid-write (``UnpicklingError: pickle data was truncated``), and multiprocessing hands it to
``sys.excepthook``, which printed a traceback after rigsfm's line: the children of this server keep quiet about a
caller that went away, and report everything else as before.
"""

import pickle
import signal
import sys

signal.signal(signal.SIGTERM, signal.SIG_DFL)
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.pthread_sigmask(signal.SIG_UNBLOCK, (signal.SIGINT, signal.SIGTERM))


def _caller_left(kind, value) -> bool:
    if issubclass(kind, (EOFError, BrokenPipeError, ConnectionResetError)):
        return True
    return issubclass(kind, pickle.UnpicklingError) and "truncated" in str(value)


def _quiet_when_the_caller_left(kind, value, traceback):
    if _caller_left(kind, value):
        return
    sys.__excepthook__(kind, value, traceback)


sys.excepthook = _quiet_when_the_caller_left
