import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))


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
