"""The workflows/ scripts run end to end on small rendered scenes and give accurate results.

Each script runs as ``python workflows/NAME.py ARGS`` would run it (``runpy``, as ``__main__``, with its
``sys.argv``), in the test's own process: the scenes of one seed share their textures (generated once per
process, ~7 s each) and the stages' forkserver starts once. Its printed lines are what a user reads.
"""

import json
import runpy
import sys
from pathlib import Path

import pytest

from rigsfm.synth.scene import SceneOptions

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)

WORKFLOWS = Path(__file__).resolve().parents[1] / "workflows"


@pytest.fixture
def run_workflow(capsys, monkeypatch):
    """``run_workflow(NAME, *ARGS)``: what ``python workflows/NAME ARGS`` prints."""

    def run(name, *args):
        path = WORKFLOWS / name
        monkeypatch.setattr(sys, "argv", [str(path), *map(str, args)])
        capsys.readouterr()
        runpy.run_path(str(path), run_name="__main__")
        return capsys.readouterr().out

    return run


def test_every_workflow_has_a_docstring_and_usage():
    for path in WORKFLOWS.glob("*.py"):
        text = path.read_text()
        assert text.startswith('"""') and "python workflows/" in text, path


def test_full_circle(run_workflow, tmp_path):
    out = run_workflow("full_circle.py", tmp_path, "--num-rigs", 6, "--image-scale", 0.5)
    accuracy = json.loads((tmp_path / "accuracy.json").read_text())
    assert accuracy["narrow"]["registered"] == accuracy["narrow"]["total"] == 6
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] <= (
        1.1 * accuracy["oracle_narrow"]["relative_rotation_deg"]["max"] + 1e-3)
    assert "narrow cameras registered: 6/6" in out
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["warnings"] == []


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_two_rigs_sixty_degrees_apart(run_workflow, tmp_path, mapper):
    out = run_workflow("two_rigs.py", tmp_path, "--mapper", mapper, "--image-scale", 0.5)
    accuracy = json.loads((tmp_path / "accuracy.json").read_text())
    assert accuracy["narrow"]["registered"] == 2
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] <= (
        1.1 * accuracy["oracle_narrow"]["relative_rotation_deg"]["max"] + 1e-3)
    assert abs(accuracy["narrow"]["distance_error_percent"]["max"]) < 0.5
    assert "narrow relative rotation error" in out


def test_global_mapper(run_workflow, tmp_path):
    out = run_workflow("global_mapper.py", tmp_path, "--num-rigs", 6, "--image-scale", 0.5)
    accuracy = json.loads((tmp_path / "accuracy.json").read_text())
    assert accuracy["narrow"]["registered"] == 6
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] <= (
        1.1 * accuracy["oracle_narrow"]["relative_rotation_deg"]["max"] + 1e-3)
    assert "global mapper: 6/6 narrow cameras" in out
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["warnings"] == []


def test_four_rig_circle_is_flagged_as_undetermined(run_workflow, tmp_path):
    """Four rigs 90 degrees apart share no point between three rigs: the images do not fix the rigs' distances.

    No accuracy is asserted: the global mapper's threads decide whether the loop closes. In 30 of 32 runs here
    it left the rig01-rig04 pair out and matched the oracle of the remaining chain (0.503 deg); in 2 it closed
    the loop, and the result was 1.3-1.4x that (better) oracle's rotation error. The warnings are the answer.
    """
    run_workflow("global_mapper.py", tmp_path, "--num-rigs", 4, "--image-scale", 0.5)
    accuracy = json.loads((tmp_path / "accuracy.json").read_text())
    assert accuracy["narrow"]["registered"] == 4
    warnings = json.loads((tmp_path / "run" / "summary.json").read_text())["warnings"]
    assert any(w.startswith("SHAPE NOT DETERMINED") for w in warnings)


def test_own_folders(run_workflow, tmp_path, rendered):
    dataset = rendered(SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.5, seed=4))
    out = run_workflow("own_folders.py", dataset.images, dataset.rigs, tmp_path / "out", "--scale", dataset.scale)
    assert "rig01/narrow/frame0000.png -> rig02/narrow/frame0000.png" in out and "F_ji" in out
    poses = json.loads((tmp_path / "out" / "narrow_poses.json").read_text())
    truth = dataset.load_ground_truth()
    a, b = (truth.find_image_with_name(f"rig0{i}/narrow/frame0000.png").projection_center() for i in (1, 2))
    true_distance = float(((a - b) ** 2).sum() ** 0.5)
    assert poses["pairs"][0]["distance_m"] == pytest.approx(true_distance, rel=0.005)


def test_crowd(run_workflow, tmp_path):
    """8 rigs round 3D persons: the run, the association of noisy true heads, their rows joined back, the report."""
    out = run_workflow("crowd.py", tmp_path)
    median = float(out.split("narrow relative rotation error: median ")[1].split()[0])
    assert median < 0.2, out  # 0.09 deg measured; the heads' association varies with the solver's last digits
    found = int(out.split("persons: ")[1].split(" found")[0])
    precision = float(out.split("precision ")[1].split(",")[0])
    recall = float(out.split("recall ")[1].split()[0])
    assert found > 400 and precision > 0.8 and recall > 0.8, out
    assert 'id="persons"' in (tmp_path / "run" / "report.html").read_text()
