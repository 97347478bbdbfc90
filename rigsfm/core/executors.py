"""Fan independent tasks out: a local process pool, or a Ray cluster. Shared by ``rigsfm track`` (one
frame registration per task) and ``rigsfm run`` (one image's features per task).

:func:`map_unordered` calls ``function(task, *shared)`` for every task and hands each result to
``on_result`` as soon as it is done (in completion order), so the caller can checkpoint or write it.
``function`` must be a module-level function (it is pickled by reference), ``shared`` picklable.

- ``local``: ``concurrent.futures.ProcessPoolExecutor`` (spawned workers; ``shared`` is sent once per
  worker through the initializer); a single task runs in this process. ``workers=1`` is one worker process: a
  C++ call in this process would hold Ctrl-C and SIGTERM until it returns (seconds a frame).
- ``ray``: ``shared`` goes into Ray's object store once; ``prepare(task)`` runs here before a task is
  sent (e.g. read its images into bytes, so the workers need no shared file system, only rigsfm and
  pycolmap installed). ``address`` connects to an existing cluster (``auto``, ``HOST:PORT`` of a head
  started with ``ray start --head``, or ``ray://HOST:10001``); without it a local Ray instance with
  ``workers`` CPUs is started and shut down afterwards. A Ray instance already initialised by the caller
  is used as it is and left running. At most ``2 x cluster CPUs`` tasks are in flight (their inputs are
  held in memory while queued).

This module imports nothing heavy (Ray is imported only when used).
"""

from __future__ import annotations

import contextlib
import enum
import logging
import os
import signal
import socket
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from rigsfm.core.errors import InputError

logger = logging.getLogger(__name__)


class Executor(enum.StrEnum):
    LOCAL = "local"  # a process pool on this machine
    RAY = "ray"  # a Ray cluster (or a local Ray instance)


OnResult = Callable[[Any], None]
RAY_CONNECT_TIMEOUT_S = 10.0
_WORKER: dict = {}


_STOPS = (signal.SIGINT, signal.SIGTERM)


def _init_worker(function: Callable, shared: tuple) -> None:
    # Started with SIGINT and SIGTERM blocked (run_local): the caller decides on Ctrl-C and kills the workers; a
    # SIGTERM to the process group ends a worker quietly, not with glog's stack trace (pycolmap is imported).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOPS)
    _one_thread_each()
    _WORKER["function"], _WORKER["shared"] = function, shared


def _one_thread_each() -> None:
    """OpenCV, BLAS and OpenMP on one thread in a worker: the pool runs one worker per core, and each library's own
    threads would only contend with the other workers (OpenBLAS's idle threads spin). The libraries loaded so far
    are limited now, those loaded later (scipy's own OpenBLAS) by the variables they read as they load."""
    import cv2
    from threadpoolctl import threadpool_limits

    os.environ["OPENBLAS_NUM_THREADS"] = os.environ["OMP_NUM_THREADS"] = "1"
    cv2.setNumThreads(1)
    threadpool_limits(limits=1)


def _call_in_worker(task: Any) -> Any:
    return _WORKER["function"](task, *_WORKER["shared"])


def _call_on_ray(function: Callable, task: Any, *shared: Any) -> Any:
    _one_thread_each()
    return function(task, *shared)


def run_local(function: Callable, tasks: Sequence, on_result: OnResult, *, workers: int, shared: tuple = ()) -> None:
    if len(tasks) <= 1:  # one worker process too for workers=1: this one then answers Ctrl-C at once
        for task in tasks:
            on_result(function(task, *shared))
        return
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from multiprocessing import resource_tracker

    from rigsfm.core.processes import _main_not_imported

    resource_tracker.ensure_running()  # first: starting it unblocks SIGINT and SIGTERM in this thread

    context = multiprocessing.get_context("spawn")  # no fork of a process holding pycolmap/OpenCV threads
    pool = ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=context,
                               initializer=_init_worker, initargs=(function, shared))
    try:
        # The workers are spawned by these submits; they inherit the blocked signals until _init_worker, and
        # do not run a caller's script again (one calling track() at top level: they died, and it hung) unless
        # the function lives there.
        in_main = getattr(function, "__module__", None) == "__main__"
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, _STOPS)
        try:
            with contextlib.nullcontext() if in_main else _main_not_imported():
                pending = {pool.submit(_call_in_worker, task) for task in tasks}
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                on_result(future.result())
    except BaseException:
        # Stopped (Ctrl-C, SIGTERM) or failed: kill the workers now; shutting down would first finish the tasks
        # they hold. Python 3.11 has no public way to (ProcessPoolExecutor.kill_workers is 3.14's).
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            process.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def import_ray():
    try:
        import ray
    except ImportError as e:
        raise InputError("--executor ray needs Ray: pip install 'ray>=2.9' (or rigsfm[ray])") from e
    return ray


def check_reachable(address: str, timeout: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse a Ray address nothing answers on, within ``timeout``: ``ray.init`` retries an unreachable GCS for
    ever, printing a warning every few seconds. ``auto`` and ``local`` are Ray's own look-ups (they fail fast)."""
    if address in ("auto", "local"):
        return
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    host = host.strip("[]")
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--address {address!r}: expected HOST:PORT, ray://HOST:PORT or auto")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as error:
        why = {ConnectionRefusedError: "connection refused: nothing listens on that port",
               TimeoutError: f"no answer within {timeout:g} s", socket.gaierror: "unknown host"}.get(
            type(error), str(error) or type(error).__name__)
        raise InputError(f"cannot reach the Ray cluster at {address} ({why}); start it there (`ray start --head "
                         f"--port {port}`), check --address, or leave --address out to use a Ray instance on this "
                         "machine") from None


def run_ray(function: Callable, tasks: Sequence, on_result: OnResult, *, workers: int, address: str | None,
            shared: tuple = (), prepare: Callable[[Any], Any] | None = None) -> None:
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        if address:
            check_reachable(address)
            try:
                ray.init(address=address, log_to_driver=False)
            except (ConnectionError, TimeoutError, RuntimeError) as error:
                raise InputError(f"cannot connect to the Ray cluster at {address}: {error}") from None
        else:
            ray.init(address="local", num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False)
    try:
        cpus = int(ray.cluster_resources().get("CPU", workers)) or 1
        logger.info("Ray: %d CPUs on %d node(s), %d tasks", cpus, len(ray.nodes()), len(tasks))
        remote = ray.remote(num_cpus=1, max_retries=1)(_call_on_ray)
        shared_refs = [ray.put(value) for value in shared]
        queue = list(tasks)
        pending: list = []
        try:
            while queue or pending:
                while queue and len(pending) < 2 * cpus:
                    task = queue.pop(0)
                    pending.append(remote.remote(function, prepare(task) if prepare else task, *shared_refs))
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    on_result(ray.get(ref))
        except BaseException:
            for ref in pending:
                ray.cancel(ref)
            raise
    finally:
        if started:
            ray.shutdown()


def check_executor(executor: str, workers: int, address: str | None) -> Executor:
    """The executor named by ``executor``; a clear error for a wrong name, address or worker count."""
    if executor not in set(Executor):
        raise InputError(f"unknown executor {executor!r}: use one of {', '.join(Executor)}")
    if address and executor != Executor.RAY:
        raise InputError("--address is the address of a Ray cluster: use it with --executor ray")
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    return Executor(executor)


def map_unordered(function: Callable, tasks: Iterable, on_result: OnResult, *, executor: str = "local",
                  workers: int = 2, address: str | None = None, shared: tuple = (),
                  prepare: Callable[[Any], Any] | None = None) -> None:
    """``on_result(function(task, *shared))`` for every task, run by the chosen executor."""
    tasks = list(tasks)
    if check_executor(executor, workers, address) == Executor.RAY:
        run_ray(function, tasks, on_result, workers=workers, address=address, shared=shared, prepare=prepare)
    else:
        run_local(function, tasks, on_result, workers=workers, shared=shared)
