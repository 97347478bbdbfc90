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

# The suite runs on one pytest-xdist worker per core (pyproject: ``-n auto --dist loadgroup``; ``-n 0`` for one
# process, e.g. under a debugger). Each module goes to one worker whole, so its module fixtures (rendered scenes,
# runs) are made once. The modules of SHARED_WORKER share one worker: they use the session's 3-rig run
# (``three_rig_run``) or start Ray, and two Ray instances started at once on one machine would compete.
SHARED_WORKER = {"test_end_to_end", "test_faults", "test_report", "test_track_rendered", "test_scale"}


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups
def pytest_collection_modifyitems(items):
    for item in items:
        module = item.path.stem
        item.add_marker(pytest.mark.xdist_group("shared" if module in SHARED_WORKER else module))


@pytest.fixture(scope="session")
def rendered(tmp_path_factory):
    """``rendered(SceneOptions) -> SyntheticDataset``: each scene rendered once per test session, for every
    module and every xdist worker (a folder of the session's base temp, a lock per scene). Read-only: a test that
    changes a scene's files renders its own with ``render_dataset``."""
    from rigsfm.synth.dataset import render_dataset

    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "scenes"
    root.mkdir(exist_ok=True)

    def render(options):
        key = hashlib.sha1(repr(options).encode()).hexdigest()[:16]
        with open(root / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another worker rendering this scene: wait for it
            if not (root / f"{key}.pickle").exists():
                dataset = render_dataset(root / key, options, overwrite=True)
                (root / f"{key}.pickle").write_bytes(pickle.dumps(dataset))
            return pickle.loads((root / f"{key}.pickle").read_bytes())

    return render


@pytest.fixture(scope="session")
def three_rig_run(tmp_path_factory):
    """The 3-rig 120° arc (seed 1, image scale 0.5) rendered once and run once through the CLI with its defaults,
    shared by test_end_to_end, test_faults, test_report and test_track_rendered: ``(dataset, out, output)``.
    Treat both as read-only: a module that writes into OUT works on :func:`copy_run`'s copy."""
    from typer.testing import CliRunner

    from rigsfm.cli import app
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    root = tmp_path_factory.mktemp("three_rigs")
    dataset = render_dataset(root / "scene", SceneOptions(num_rigs=3, arc_deg=120.0, image_scale=0.5, seed=1))
    out = root / "out"
    result = CliRunner().invoke(app, ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale",
                                      str(dataset.scale), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return dataset, out, result.output


def copy_run(out: Path, where: Path) -> Path:
    """A private copy of a finished workspace (same files, another path)."""
    shutil.copytree(out, where)
    return where
