"""Arena scale: pairs chosen by a first pass, the skipped-pair check, SIFT on a real Ray cluster, the GPU decision.

The rendered tests use an 8-rig full circle (image_scale 0.5) run with ``neighbours=2`` so that pairs are
actually skipped; the Ray test starts a head and a second node with ``ray start`` on this machine.
"""

from __future__ import annotations

import json
import operator
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rigsfm.core.errors import InputError
from rigsfm.core.executors import Executor, check_executor, map_unordered
from rigsfm.run.checks.missed_pairs import missed_pairs
from rigsfm.run.inputs.database import create_database
from rigsfm.run.matching.extract import _extraction_options, extract_features, extract_one
from rigsfm.run.matching.feature_cache import FEATURE_CACHE_ENV
from rigsfm.run.matching.gpu import cuda_device_count, decide, pycolmap_device, use_gpu
from rigsfm.run.matching.pairs import PairSelection, _spanning_tree, first_pass_scores
from rigsfm.run.options import Device, MatchingOptions, Pairs, RunOptions
from rigsfm.run.pipeline import load_inputs, run
from rigsfm.synth.demo import score
from rigsfm.synth.scene import SceneOptions

REPO = Path(__file__).resolve().parent.parent
NUM_RIGS = 8


# --- no images needed -------------------------------------------------------------------------------------


def test_gpu_decision():
    assert decide(Device.CPU, has_cuda=True, num_devices=1) is False
    assert decide(Device.AUTO, has_cuda=False, num_devices=4) is False  # plain pycolmap: the CPU, silently
    assert decide(Device.AUTO, has_cuda=True, num_devices=0) is False  # CUDA build, no GPU
    assert decide(Device.AUTO, has_cuda=True, num_devices=1) is True
    assert decide("cuda", has_cuda=True, num_devices=2) is True
    with pytest.raises(InputError, match=r"rigsfm\[gpu\]"):
        decide(Device.CUDA, has_cuda=False, num_devices=1)
    with pytest.raises(InputError, match="no CUDA device"):
        decide(Device.CUDA, has_cuda=True, num_devices=0)
    # This machine: GPU SIFT exactly when pycolmap is the CUDA build and the driver reports a device.
    assert use_gpu(Device.AUTO) == (bool(pycolmap.has_cuda) and cuda_device_count() > 0)
    assert use_gpu(Device.CPU) is False


def test_pycolmap_device_is_named_for_each_decision():
    """pycolmap's own default (Device.auto) would run a CUDA build on the GPU whatever the options say."""
    assert pycolmap_device(False) == pycolmap.Device.cpu
    assert pycolmap_device(True) == pycolmap.Device.cuda


def test_device_cpu_extracts_on_the_cpu(rendered, tmp_path):
    """--device cpu gives the CPU's SIFT, bit for bit, also with pycolmap's CUDA build on a GPU machine (where
    pycolmap's default device put the extraction on the GPU): the workspace's record of the device is then true."""
    dataset = rendered(SceneOptions(num_rigs=2, image_scale=0.3, seed=0))
    inputs = load_inputs(dataset.images, dataset.rigs)
    name = sorted(e.name for e in inputs.images if e.sensor == "wide")[0]
    options = MatchingOptions(device=Device.CPU)
    db_path = create_database(tmp_path / "database.db", inputs.rigs, inputs.images)
    extract_features(db_path, dataset.images, [e for e in inputs.images if e.name == name], options, num_threads=1)
    with pycolmap.Database.open(db_path) as db:
        image_id = db.read_image_with_name(name).image_id
        keypoints, descriptors = db.read_keypoints(image_id), db.read_descriptors(image_id).data
    cpu = _extraction_options(options, num_threads=1, first_octave=-1)
    assert cpu.use_gpu is False
    features = extract_one((name, (dataset.images / name).read_bytes(), ".png"), cpu)  # Device.cpu, explicitly
    assert len(keypoints) > 100
    np.testing.assert_array_equal(features.keypoints, keypoints)
    np.testing.assert_array_equal(features.descriptors, descriptors)


def test_first_pass_counts_shared_features():
    rng = np.random.default_rng(0)

    def unit(n):
        x = rng.random((n, 128)).astype(np.float32) ** 4  # SIFT-like: non-negative, peaky
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    a = unit(200)
    shared = a[:60] + 0.02 * unit(60)  # 60 of a's features seen again, slightly changed, in another order
    b = np.vstack([unit(90), shared[::-1]])
    c = unit(120)  # nothing in common, and fewer features than the others (padding)
    scores = first_pass_scores({"a": a, "b": b, "c": c}, [("a", "b"), ("a", "c"), ("b", "c")])
    assert 55 <= scores[("a", "b")] <= 60
    assert scores[("a", "c")] <= 5 and scores[("b", "c")] <= 5


def test_spanning_tree_keeps_the_strongest_links():
    edges = {("r1", "r2"): 90, ("r2", "r3"): 80, ("r1", "r3"): 70, ("r3", "r4"): 5}
    assert _spanning_tree(["r1", "r2", "r3", "r4"], edges) == [("r1", "r2"), ("r2", "r3"), ("r3", "r4")]


def test_local_executor_runs_every_task_in_worker_processes():
    results = []
    map_unordered(operator.pow, range(6), results.append, executor="local", workers=2, shared=(2,))
    assert sorted(results) == [0, 1, 4, 9, 16, 25]
    with pytest.raises(InputError, match="--address"):
        check_executor("local", 2, "127.0.0.1:6379")
    with pytest.raises(InputError, match="unknown executor"):
        check_executor("dask", 2, None)
    assert check_executor("ray", 1, None) == Executor.RAY


def test_local_executor_workers_run_their_libraries_on_one_thread():
    """One worker per core: OpenBLAS (numpy's and scipy's, loaded later), OpenMP and OpenCV on one thread each, not
    one per core in every worker (on a 1-core machine this holds anyway)."""
    from support import worker_threads

    results = []
    map_unordered(worker_threads, range(2), results.append, executor="local", workers=2)
    assert results[0] and all(threads == 1 for result in results for _, threads in result), results


def test_local_executor_does_not_run_the_callers_script_again(tmp_path):
    """A script calling the library at top level, as docs show `track(OUT, NEW, TrackOptions())`, without
    `if __name__ == "__main__"`: the spawned workers must not execute it again (they did, and track hung)."""
    marks = tmp_path / "marks.txt"
    script = tmp_path / "script.py"
    script.write_text(
        "import operator\n"
        "from rigsfm.core.executors import map_unordered\n"
        f"with open({str(marks)!r}, 'a') as f:\n"
        "    f.write('ran\\n')\n"
        "results = []\n"
        "map_unordered(operator.pow, range(4), results.append, executor='local', workers=2, shared=(2,))\n"
        "print(sorted(results))\n")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[0, 1, 4, 9]"
    assert marks.read_text() == "ran\n"


# --- an 8-rig circle ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def circle(tmp_path_factory, rendered):
    root = tmp_path_factory.mktemp("scale")
    dataset = rendered(SceneOptions(num_rigs=NUM_RIGS, image_scale=0.5, seed=0))
    options = RunOptions(matching=MatchingOptions(pairs=Pairs.AUTO, neighbours=2), num_threads=2)
    result = run(dataset.images, dataset.rigs, root / "out", dataset.scale, options)
    return dataset, root, result


def _wide(rig: int) -> str:
    return f"rig{rig:02d}/wide/frame0000.png"


@pytest.mark.slow  # the rendered 8-rig circle
def test_auto_pairs_keep_each_rigs_circle_neighbours(circle):
    _, root, result = circle
    pairs = json.loads((root / "out" / "summary.json").read_text())["pairs"]
    assert pairs["mode"] == "auto" and pairs["candidates"] == NUM_RIGS * (NUM_RIGS - 1) // 2
    assert pairs["matched"] <= 2 * NUM_RIGS and pairs["skipped"] >= 12
    with pycolmap.Database.open(root / "out" / "database.db") as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        matched = {tuple(sorted(names[i] for i in pycolmap.pair_id_to_image_pair(p)))
                   for p in db.read_two_view_geometry_num_inliers()[0]}
    truth = pycolmap.Reconstruction(circle[0].ground_truth)
    centre = {im.name: im.projection_center() for im in truth.images.values()}
    for rig in range(1, NUM_RIGS + 1):  # the true nearest rig on either side is matched
        others = [r for r in range(1, NUM_RIGS + 1) if r != rig]
        nearest = min(others, key=lambda r: np.linalg.norm(centre[_wide(r)] - centre[_wide(rig)]))
        assert tuple(sorted((_wide(rig), _wide(nearest)))) in matched
    assert len(matched) == pairs["matched"]


@pytest.mark.slow  # the rendered 8-rig circle
def test_auto_pairs_reach_the_oracle(circle):
    dataset, _, result = circle
    accuracy = score(result, dataset)
    run_, limit = accuracy["narrow"], accuracy["oracle_narrow"]
    assert run_["registered"] == NUM_RIGS
    assert run_["relative_rotation_deg"]["median"] <= 1.05 * limit["relative_rotation_deg"]["median"]
    assert run_["distance_error_percent"]["median"] <= 1.05 * limit["distance_error_percent"]["median"]
    assert run_["relative_rotation_deg"]["max"] < 0.6
    assert not [w for w in result.summary.warnings if w.startswith("PAIRS MISSED")]


@pytest.mark.slow  # the rendered 8-rig circle
def test_a_skipped_strong_pair_is_flagged(circle):
    """Skip rig01-rig02 (45 degrees apart) but match every pair 90 degrees apart: the model says the skipped
    pair shares over twice the points of those (1892 vs 784-871 here), so it is reported; the run's own
    selection reports nothing. (Pairs 135 degrees apart share no point seen within 40 degrees: matched pairs that
    share nothing in the model set no bar.)"""
    _, _, result = circle
    reconstruction = result.reconstruction
    n = NUM_RIGS
    near = [(_wide(i), _wide(i % n + 1)) for i in range(1, n + 1)]
    far = [(_wide(i), _wide((i + 1) % n + 1)) for i in range(1, n + 1)]
    pairs = [tuple(sorted(p)) for p in near[1:] + far]
    skipped = tuple(sorted(near[0]))
    selection = PairSelection(Pairs.AUTO, pairs, 28, {p: 0 for p in [*pairs, skipped]})
    missed = missed_pairs(reconstruction, selection)
    assert [(m.image_a, m.image_b) for m in missed] == [skipped]
    assert missed[0].predicted_points > 2 * missed[0].weakest_matched > 0
    exhaustive = PairSelection(Pairs.EXHAUSTIVE, [*pairs, skipped], 28)
    assert missed_pairs(reconstruction, exhaustive) == []


@pytest.mark.slow  # the rendered 8-rig circle
def test_extract_one_scales_large_images_like_colmap(circle, tmp_path):
    """A 400-pixel limit makes COLMAP scale the 812-pixel images down; one task must do exactly the same."""
    dataset, _, _ = circle
    inputs = load_inputs(dataset.images, dataset.rigs)
    name = _wide(3)
    extraction = _extraction_options(MatchingOptions(), num_threads=1, first_octave=-1)
    extraction.max_image_size = 400
    db_path = create_database(tmp_path / "database.db", inputs.rigs, inputs.images)
    pycolmap.extract_features(db_path, dataset.images, image_names=[name], camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              extraction_options=extraction)
    with pycolmap.Database.open(db_path) as db:
        image_id = db.read_image_with_name(name).image_id
        keypoints, descriptors = db.read_keypoints(image_id), db.read_descriptors(image_id).data
    features = extract_one((name, (dataset.images / name).read_bytes(), ".png"), extraction)
    assert len(keypoints) > 300 and keypoints[:, 0].max() > 700  # scaled back to full-size pixels
    np.testing.assert_array_equal(features.keypoints, keypoints)
    np.testing.assert_array_equal(features.descriptors, descriptors)


# --- a real Ray cluster: a head and a second node, started with `ray start` on this machine -----------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(process: subprocess.Popen) -> None:
    """End the process group this test started (``ray start --block`` and what it spawned), by its id. A node
    leaves within a second of SIGTERM; the head then drains for up to 30 s (Ray 2.60) for a cluster that is gone,
    which the test does not wait for (it used to wait 15 s of it)."""
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=3)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        pass
    try:
        os.killpg(process.pid, signal.SIGKILL)  # what is left of the group
    except ProcessLookupError:
        pass
    process.wait()


@pytest.fixture
def ray_cluster(tmp_path):
    ray = pytest.importorskip("ray")
    ray_cli = Path(sys.executable).with_name("ray")
    if not ray_cli.exists():
        pytest.skip("the ray command is not installed next to this Python")
    # Ray 2.5x's `ray start` asks clients for a token by default; this loopback test cluster opts out (the
    # driver, this process, may have imported Ray before any setting could reach it).
    env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    port = _free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus=1", "--disable-usage-stats", "--block"]
    processes = []
    try:
        processes.append(subprocess.Popen(
            [str(ray_cli), "start", "--head", f"--port={port}", "--include-dashboard=false", *common], env=env,
            stdout=open(tmp_path / "head.log", "w"), stderr=subprocess.STDOUT, start_new_session=True))
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and "Ray runtime started" not in (tmp_path / "head.log").read_text():
            assert processes[0].poll() is None, (tmp_path / "head.log").read_text()
            time.sleep(1)
        processes.append(subprocess.Popen(
            [str(ray_cli), "start", f"--address={address}", *common], env=env,
            stdout=open(tmp_path / "node.log", "w"), stderr=subprocess.STDOUT, start_new_session=True))
        ray.init(address=address, log_to_driver=False)
        while time.monotonic() < deadline and sum(n["Alive"] for n in ray.nodes()) < 2:
            time.sleep(1)
        assert sum(n["Alive"] for n in ray.nodes()) == 2, (tmp_path / "node.log").read_text()
        yield address
    finally:
        if ray.is_initialized():
            ray.shutdown()
        for process in reversed(processes):
            _stop(process)


@pytest.mark.slow
def test_ray_cluster_features_are_bit_identical(circle, ray_cluster, tmp_path, monkeypatch):
    """Every featured image extracted on a two-node Ray cluster (one CPU each) equals the local extraction."""
    import ray

    monkeypatch.delenv(FEATURE_CACHE_ENV)  # extracted on the cluster, not read from the session's cache

    dataset, root, _ = circle
    assert ray.cluster_resources()["CPU"] == 2
    ray.shutdown()  # extract_features connects to the cluster itself, as `rigsfm run --address` does
    inputs = load_inputs(dataset.images, dataset.rigs)
    db_path = create_database(tmp_path / "database.db", inputs.rigs, inputs.images)
    count = extract_features(db_path, dataset.images, inputs.images, MatchingOptions(), executor="ray",
                             address=ray_cluster)
    assert count == NUM_RIGS
    with pycolmap.Database.open(db_path) as remote, pycolmap.Database.open(root / "out" / "database.db") as local:
        for entry in inputs.images:
            if entry.sensor != "wide":
                assert not remote.exists_keypoints(remote.read_image_with_name(entry.name).image_id)
                continue
            a, b = remote.read_image_with_name(entry.name).image_id, local.read_image_with_name(entry.name).image_id
            assert remote.read_keypoints(a).shape[0] > 1000
            np.testing.assert_array_equal(remote.read_keypoints(a), local.read_keypoints(b))
            np.testing.assert_array_equal(remote.read_descriptors(a).data, local.read_descriptors(b).data)
