"""rigsfm.core.processes: a stage function in a child process, stopped at once by the caller's signals."""

import logging
import os
import pickle
import signal
import time

import numpy as np
import pycolmap
import pytest

from rigsfm.core import processes as stages
from rigsfm.core.errors import InputError
from rigsfm.core.processes import StageDied, in_child


# Stage functions must be importable by name: module level.
def _add(a, b, *, scale=1):
    return (a + b) * scale, os.getpid()


def _report(n, progress):
    for i in range(n):
        progress(i + 1, n)
    return "done"


def _log(message):
    logging.getLogger("rigsfm.test_stages").warning("from the child: %s", message)
    logging.getLogger("rigsfm.test_stages").debug("not kept: the caller keeps warnings only")
    os.write(2, b"fd2 line from the child\n")


def _fail():
    raise InputError("rigs.yaml: rig01 has no narrow camera; add one")


class _NotPicklable(Exception):
    def __init__(self, a, b):
        super().__init__(f"{a} {b}")


def _fail_unpicklable():
    raise _NotPicklable(1, 2)


def _die():
    os._exit(3)


def _block_until_stopped(started):
    """Tells the caller its pid, then stays in one C call without the GIL's help, as pycolmap's mapper does."""
    started(os.getpid())
    time.sleep(600)
    return "not stopped"


def _echo(value):
    return value


def test_result_arguments_and_child_process():
    value, pid = in_child(_add, 2, 3, scale=10)
    assert value == 50
    assert pid != os.getpid()


def _allocate(megabytes):
    import numpy as np

    block = np.ones(int(megabytes * 2**20 // 8))  # touched: resident
    return float(block[-1]), stages.cpu_seconds()


def test_cpu_seconds_and_peak_memory_of_stage_processes_are_counted():
    cpu_before, peak_before = stages.stage_cpu_seconds(), stages.stage_peak_rss_mb()
    _, child_cpu = in_child(_allocate, peak_before + 300)  # more than this process ever held
    assert stages.stage_peak_rss_mb() >= peak_before + 300 > stages.peak_rss_mb()
    assert stages.stage_cpu_seconds() - cpu_before >= child_cpu > 0


def test_in_process_switch_runs_in_the_caller():
    with stages.in_process():
        assert in_child(_add, 1, 1)[1] == os.getpid()
    assert in_child(_add, 1, 1)[1] != os.getpid()


def test_callables_are_called_in_the_caller():
    calls = []
    assert in_child(_report, 3, lambda done, total: calls.append((done, total))) == "done"
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_log_records_and_fd2_reach_the_caller(caplog, capfd):
    with caplog.at_level(logging.WARNING, logger="rigsfm.test_stages"):
        in_child(_log, "hello")
    messages = [r.getMessage() for r in caplog.records if r.name == "rigsfm.test_stages"]
    assert messages == ["from the child: hello"]
    assert "fd2 line from the child" in capfd.readouterr().err


def test_errors_keep_their_type_and_message():
    with pytest.raises(InputError, match="rig01 has no narrow camera"):
        in_child(_fail)
    with pytest.raises(RuntimeError, match="_NotPicklable: 1 2"):
        in_child(_fail_unpicklable)


def test_a_child_that_dies_is_a_one_line_error():
    with pytest.raises(StageDied, match="_die stage stopped without a result .exit code 3"):
        in_child(_die)


def test_reconstruction_travels_exactly():
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_RADIAL, 812.5, 812, 617)
    reconstruction.add_camera(camera)
    rng = np.random.default_rng(0)
    for _ in range(50):
        reconstruction.add_point3D(rng.normal(size=3) * 7.0, pycolmap.Track(), np.array([1, 2, 3], np.uint8))
    copy = in_child(_echo, reconstruction)
    assert copy.cameras[1].params.tolist() == camera.params.tolist()
    assert sorted(copy.points3D) == sorted(reconstruction.points3D)
    for point_id, point in reconstruction.points3D.items():
        assert copy.points3D[point_id].xyz.tolist() == point.xyz.tolist()
    assert pickle.loads(pickle.dumps(copy)).num_points3D() == 50


def test_an_exception_in_the_caller_kills_the_child():
    """A signal handler that raises (Ctrl-C here) ends the wait at once, and the child with it."""
    pids = []

    def started(pid):
        pids.append(pid)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the child sleeps in C

    # Python's own Ctrl-C handler, also where SIGINT came in ignored (a job started with `&` by a shell without
    # job control, as CI runners may: the test would wait for the child's 600 s sleep).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            in_child(_block_until_stopped, started)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(pids) == 1 and pids[0] != os.getpid()
    with pytest.raises(ProcessLookupError):  # killed and reaped, not left running
        os.kill(pids[0], 0)


@pytest.mark.parametrize("sent", [0, 30], ids=["nothing", "half its work"])
def test_a_child_whose_caller_left_during_its_start_prints_nothing(tmp_path, sent):
    """A signal that stops rigsfm inside ``Process.start`` leaves the forked child without its work, or with part
    of it: it used to print multiprocessing's EOFError or "pickle data was truncated" traceback after rigsfm's one
    line (test_interrupt's signals, now and then). Here the caller leaves at exactly that point: it asks the
    forkserver for a child, writes ``sent`` bytes of a 60-byte pickle and closes the pipe."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "leave.py"
    script.write_text(
        "import os, pickle, sys, time\n"
        "from multiprocessing import forkserver\n"
        "from rigsfm.core import processes as stages\n"
        "stages.start()\n"
        "_, work = forkserver._forkserver.connect_to_new_process([])\n"
        f"os.write(work, pickle.dumps('x' * 45)[:{sent}])\n"
        "os.close(work)\n"
        "time.sleep(1.0)\n"  # the child reads, fails and exits meanwhile
        "print('left', file=sys.stderr)\n")
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(root), "GLOG_minloglevel": "2"})
    assert done.returncode == 0 and done.stderr.strip().splitlines()[-1] == "left", done.stderr
    assert "Traceback" not in done.stderr and "Error" not in done.stderr, done.stderr
