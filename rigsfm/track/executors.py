"""Fan the independent per-frame registrations out: a local process pool, or a Ray cluster.

Both call :func:`rigsfm.track.register.register_frame` with picklable inputs and hand each record to
``on_result`` as soon as it is done (in completion order), so the caller can checkpoint.

- ``local``: ``concurrent.futures.ProcessPoolExecutor`` (spawned workers; the reference map is sent
  once per worker through the initializer); ``workers=1`` runs in this process.
- ``ray``: the reference map goes into Ray's object store once; images are read here and sent as bytes,
  so the workers need no shared file system (only rigsfm and pycolmap installed). ``address`` connects to
  an existing cluster (e.g. ``ray://head:10001`` or ``auto``); without it a local Ray instance with
  ``workers`` CPUs is started and shut down afterwards. A Ray instance already initialised by the caller
  is used as it is and left running.
"""

from __future__ import annotations

import logging
import multiprocessing
import socket
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import replace
from pathlib import Path

from rigsfm.core.errors import InputError
from rigsfm.track.options import RegistrationOptions
from rigsfm.track.reference import ReferenceMap
from rigsfm.track.register import FrameTask, register_frame

logger = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
OnResult = Callable[[dict], None]
RAY_CONNECT_TIMEOUT_S = 10.0

_WORKER: dict = {}


def _init_worker(reference: ReferenceMap, options: RegistrationOptions) -> None:
    import cv2

    cv2.setNumThreads(1)
    _WORKER["reference"], _WORKER["options"] = reference, options


def _register_in_worker(task: FrameTask) -> dict:
    return register_frame(task, _WORKER["reference"], _WORKER["options"])


def run_local(tasks: Sequence[FrameTask], reference: ReferenceMap, options: RegistrationOptions, workers: int,
              on_result: OnResult) -> None:
    if workers <= 1 or len(tasks) <= 1:
        for task in tasks:
            on_result(register_frame(task, reference, options))
        return
    context = multiprocessing.get_context("spawn")  # no fork of a process holding pycolmap/OpenCV threads
    with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=context,
                             initializer=_init_worker, initargs=(reference, options)) as pool:
        pending = {pool.submit(_register_in_worker, task) for task in tasks}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    on_result(future.result())
        except BaseException:
            for future in pending:
                future.cancel()
            raise


def _register_bytes(task: FrameTask, reference: ReferenceMap, options: RegistrationOptions) -> dict:
    import cv2

    cv2.setNumThreads(1)
    return register_frame(task, reference, options)


def _with_bytes(task: FrameTask) -> FrameTask:
    images = {}
    for sensor, source in task.images.items():
        try:
            images[sensor] = Path(source).read_bytes() if isinstance(source, (str, Path)) else source
        except OSError as e:
            raise InputError(f"cannot read {source}: {e}") from e
    return replace(task, images=images)


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


def run_ray(tasks: Sequence[FrameTask], reference: ReferenceMap, options: RegistrationOptions, workers: int,
            address: str | None, on_result: OnResult) -> None:
    try:
        import ray
    except ImportError as e:
        raise InputError("--executor ray needs Ray: pip install 'ray>=2.9' (or rigsfm[ray])") from e
    started = not ray.is_initialized()
    if started:
        if address:
            check_reachable(address)
            try:
                ray.init(address=address, log_to_driver=False)
            except (ConnectionError, TimeoutError, RuntimeError) as error:
                raise InputError(f"cannot connect to the Ray cluster at {address}: {error}") from None
        else:
            ray.init(num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False)
    try:
        cpus = int(ray.cluster_resources().get("CPU", workers)) or 1
        logger.info("Ray: %d CPUs, %d frames", cpus, len(tasks))
        remote = ray.remote(num_cpus=1, max_retries=1)(_register_bytes)
        reference_ref, options_ref = ray.put(reference), ray.put(options)
        queue, pending = list(tasks), []
        try:
            while queue or pending:
                while queue and len(pending) < 2 * cpus:  # bounded: images are held in memory while queued
                    pending.append(remote.remote(_with_bytes(queue.pop(0)), reference_ref, options_ref))
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


def run_frames(tasks: Sequence[FrameTask], reference: ReferenceMap, on_result: OnResult, *,
               executor: str = "local", workers: int = 2, address: str | None = None,
               options: RegistrationOptions | None = None) -> None:
    """Register every task with the chosen executor; ``on_result`` gets each record when it is done."""
    options = options or RegistrationOptions()
    if executor not in EXECUTORS:
        raise InputError(f"unknown executor {executor!r}: use one of {', '.join(EXECUTORS)}")
    if address and executor != "ray":
        raise InputError("--address is the address of a Ray cluster: use it with --executor ray")
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if executor == "ray":
        run_ray(tasks, reference, options, workers, address, on_result)
    else:
        run_local(tasks, reference, options, workers, on_result)
