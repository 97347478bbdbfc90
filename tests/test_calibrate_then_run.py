"""Calibrate the arena's rigs from rendered ChArUco views, then run the pipeline with the written rigs.yaml."""

import numpy as np
import pycolmap
import pytest
import yaml
from typer.testing import CliRunner

from rigsfm.calibrate.board import board_spec_from_dict
from rigsfm.cli import app
from rigsfm.core.conventions import opencv_from_colmap_pixels, rotation_angle_deg
from rigsfm.core.rig import load_rigs
from rigsfm.run.pipeline import RunResult
from rigsfm.synth.boards import HybridRig, SynthCamera, board_views, write_board_dataset
from rigsfm.synth.demo import score
from rigsfm.synth.scene import SceneOptions

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)

BOARD = {"type": "charuco", "squares": [11, 8], "square": 0.06, "marker": 0.045, "dictionary": "DICT_5X5_100"}


def synth_camera(camera) -> SynthCamera:
    """The arena's COLMAP OPENCV camera as an OpenCV camera (principal point moved by -0.5)."""
    fx, fy, cx, cy, k1, k2, p1, p2 = camera.params
    cx, cy = opencv_from_colmap_pixels(np.array([cx, cy]))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return SynthCamera(K, np.array([k1, k2, p1, p2, 0.0]), (camera.width, camera.height))


def test_calibrated_rigs_yaml_drives_a_run(tmp_path, rendered):
    dataset = rendered(SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.5, seed=2))
    exact = load_rigs(dataset.rigs_exact)
    spec = board_spec_from_dict(BOARD)
    for index, rig in enumerate(exact):
        hybrid = HybridRig(synth_camera(rig.wide), synth_camera(rig.narrow),
                           rig.narrow_from_wide.rotation.matrix(), np.asarray(rig.narrow_from_wide.translation))
        write_board_dataset(tmp_path / "BOARD", rig.name, spec, hybrid,
                            board_views(np.random.default_rng(index), 16, 6), seed=index)
    (tmp_path / "board.yaml").write_text(yaml.safe_dump(BOARD))
    rigs_yaml = tmp_path / "rigs.yaml"
    runner = CliRunner()
    calibrated = runner.invoke(app, ["calibrate", str(tmp_path / "BOARD"), "--board", str(tmp_path / "board.yaml"),
                                     "--out", str(rigs_yaml)])
    assert calibrated.exit_code == 0, calibrated.output

    for ours, truth in zip(load_rigs(rigs_yaml), exact):
        assert ours.name == truth.name
        for sensor in ("wide", "narrow"):
            focal_error = np.abs(np.array(ours.camera(sensor).params[:2]) / truth.camera(sensor).params[:2] - 1)
            assert focal_error.max() < 0.003, (sensor, focal_error)
        assert rotation_angle_deg(ours.narrow_from_wide.rotation.matrix(),
                                  truth.narrow_from_wide.rotation.matrix()) < 0.1
        assert np.linalg.norm(ours.narrow_from_wide.translation - truth.narrow_from_wide.translation) < 0.002
        print(f"{ours.name}: focal errors (%) "
              f"{np.round(100 * (np.r_[ours.wide.params[:2], ours.narrow.params[:2]] / np.r_[truth.wide.params[:2], truth.narrow.params[:2]] - 1), 4)}, "
              f"E^sl rotation error {rotation_angle_deg(ours.narrow_from_wide.rotation.matrix(), truth.narrow_from_wide.rotation.matrix()):.4f} deg, "
              f"translation error {1000 * np.linalg.norm(ours.narrow_from_wide.translation - truth.narrow_from_wide.translation):.3f} mm")

    out = tmp_path / "out"
    ran = runner.invoke(app, ["run", str(dataset.images), "--rigs", str(rigs_yaml), "--scale", str(dataset.scale),
                              "--out", str(out)])
    assert ran.exit_code == 0, ran.output
    accuracy = score(RunResult(None, pycolmap.Reconstruction(out / "sparse"), {}), dataset)
    print(f"calibrate->run: narrow rotation error {accuracy['narrow']['relative_rotation_deg']['max']:.4f} deg, "
          f"distance error {accuracy['narrow']['distance_error_percent']['max']:.4f} %")
    assert accuracy["narrow"]["registered"] == 2
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] < 0.3
    assert abs(accuracy["narrow"]["distance_error_percent"]["max"]) < 0.5
