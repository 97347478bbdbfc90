import fcntl
import hashlib
import os
import pickle
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
# pytest-xdist's workers start with COLUMNS=80, and rich fixes its consoles' width when rigsfm.cli is imported:
# the CLI tests set their own width (COLUMNS in CliRunner's env), which needs the width left open here.
os.environ.pop("COLUMNS", None)


def pytest_configure(config):
    """With one xdist worker per core, the workers' BLAS (OpenBLAS) and OpenMP (Open3D) thread pools only compete:
    OpenBLAS's threads spin while they wait. One thread each, set here before any worker starts (the workers and
    every process they start inherit it): the suite took 10 min 54 s instead of 11 min 39-45 s on 2 cores, the
    board calibrations 118 instead of 129 s. ``-n 0`` (one process) keeps the libraries' defaults."""
    workers = getattr(config.option, "numprocesses", None)
    if isinstance(workers, int) and workers > 1 and not os.environ.get("PYTEST_XDIST_WORKER"):
        for variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(variable, "1")


# The suite runs on one pytest-xdist worker per core (pyproject: ``-n auto``; ``-n 0`` for one process, e.g. under
# a debugger), one test module per work unit (tests/scheduling.py), so its module fixtures (rendered scenes, runs)
# are made once. Scenes and the 3-rig run are shared by every worker through files (``rendered``, ``three_rig_run``).
def pytest_xdist_make_scheduler(config, log):
    from scheduling import ModuleScheduling

    return ModuleScheduling(config, log)


def _shared_root(tmp_path_factory) -> Path:
    """A folder every xdist worker of this session sees (the workers' common base temp)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared"
    root.mkdir(exist_ok=True)
    return root


def _once(root: Path, key: str, make):
    """``make(folder)``'s picklable result, made by the first worker that asks for ``key`` in this session
    (the others wait on its lock and read it back)."""
    with open(root / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = root / f"{key}.pickle"
        if not done.exists():
            done.write_bytes(pickle.dumps(make(root / key)))
        return pickle.loads(done.read_bytes())


@pytest.fixture(scope="session", autouse=True)
def shared_caches(tmp_path_factory):
    """Made once per session, for every worker and every process they start: the synthetic scenes' textures
    (~6-9 s per seed and process; rigsfm.synth.scene, RIGSFM_TEXTURE_CACHE) and the features of each rendered
    image (many tests run the same scenes into new workspaces; rigsfm.run.matching.feature_cache, RIGSFM_FEATURE_CACHE).
    A test of extraction itself unsets the latter (``monkeypatch.delenv``)."""
    from rigsfm.run.matching.feature_cache import FEATURE_CACHE_ENV
    from rigsfm.synth.scene import TEXTURE_CACHE_ENV

    os.environ[TEXTURE_CACHE_ENV] = str(_shared_root(tmp_path_factory) / "textures")
    os.environ[FEATURE_CACHE_ENV] = str(_shared_root(tmp_path_factory) / "features")


@pytest.fixture(scope="session")
def rendered(tmp_path_factory):
    """``rendered(SceneOptions) -> SyntheticDataset``: each scene rendered once per test session, for every
    module and every xdist worker. Read-only: a test that changes a scene's files renders its own with
    ``render_dataset``."""
    from rigsfm.synth.dataset import render_dataset

    root = _shared_root(tmp_path_factory)

    def render(options):
        key = hashlib.sha1(repr(options).encode()).hexdigest()[:16]
        return _once(root, key, lambda folder: render_dataset(folder, options, overwrite=True))

    return render


@pytest.fixture(scope="session")
def three_rig_run(tmp_path_factory):
    """The 3-rig 120° arc (seed 1, image scale 0.5) rendered once and run once through the CLI with its defaults,
    for the whole session (every xdist worker), shared by test_end_to_end, test_faults, test_report and
    test_track_rendered: ``(dataset, out, output)``. Treat both as read-only: a module that writes into OUT works
    on :func:`copy_run`'s copy."""
    from typer.testing import CliRunner

    from rigsfm.cli import app
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    def make(root: Path):
        dataset = render_dataset(root / "scene", SceneOptions(num_rigs=3, arc_deg=120.0, image_scale=0.5, seed=1))
        out = root / "out"
        result = CliRunner().invoke(app, ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale",
                                          str(dataset.scale), "--out", str(out)])
        assert result.exit_code == 0, result.output
        return dataset, out, result.output

    return _once(_shared_root(tmp_path_factory), "three_rigs", make)


def copy_run(out: Path, where: Path) -> Path:
    """A private copy of a finished workspace (same files, another path)."""
    shutil.copytree(out, where)
    return where
