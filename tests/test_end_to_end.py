"""`rigsfm run` through the CLI on a small rendered scene, checked against the exact ground truth."""

import json
import shutil
import subprocess

import numpy as np
import pycolmap
import pytest
from conftest import copy_run
from typer.testing import CliRunner

from rigsfm.calibrate.uncertainty import load_sigmas
from rigsfm.cli import app
from rigsfm.core.conventions import rotation_from_euler_zyx_degrees
from rigsfm.core.rig import load_rigs
from rigsfm.run.pipeline import RunResult
from rigsfm.synth.demo import score

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)


@pytest.fixture(scope="module")
def scene(three_rig_run, tmp_path_factory):
    dataset, shared, output = three_rig_run  # the session's run (conftest), copied: these tests re-run in OUT
    out = copy_run(shared, tmp_path_factory.mktemp("e2e") / "out")
    args = ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale", str(dataset.scale),
            "--out", str(out)]
    return dataset, out, args, output


def test_every_camera_registered_metric_and_reported(scene):
    dataset, out, _, output = scene
    summary = json.loads((out / "summary.json").read_text())
    assert summary["registered"] == {"wide": {"registered": 3, "total": 3}, "narrow": {"registered": 3, "total": 3}}
    assert summary["metric"] is True and summary["scale"]["source"] == "measurements"
    distance, = [m for m in summary["scale"]["measurements"] if m["kind"] == "camera_distance"]
    assert abs(distance["residual_percent"]) < 0.1
    assert set(summary["timings_s"]) == {"validate", "database", "features", "matching", "mapping",
                                         "adjust", "world", "narrow_observations", "uncertainty", "deliver",
                                         "check_pairs", "self_check"}
    for camera, row in summary["reprojection_error"].items():
        if camera.endswith("/wide"):
            assert row["observations"] > 300 and row["mean_px"] < 0.5
    assert "registered: wide 3/3, narrow 3/3" in output


def test_accuracy_within_ten_percent_of_the_oracle(scene):
    dataset, out, _, _ = scene
    result = RunResult(None, pycolmap.Reconstruction(out / "sparse"), {})
    accuracy = score(result, dataset)
    run_, limit = accuracy["narrow"], accuracy["oracle_narrow"]
    assert run_["registered"] == 3
    assert run_["relative_rotation_deg"]["max"] <= 1.1 * limit["relative_rotation_deg"]["max"] + 1e-3
    assert run_["relative_rotation_deg"]["max"] < 0.3
    assert run_["distance_error_percent"]["max"] < 0.5


def test_model_refines_only_what_the_images_see(scene):
    """Featureless narrow views: their intrinsics and E^sl are not in the adjustment and stay exactly as calibrated
    (narrow pose = E^sl * wide pose: no scale trap); the wide intrinsics of a rig whose refinement summary.json and
    the terminal report move, within 3 sigma of rigs.yaml's, and a held rig's stay exactly as calibrated."""
    dataset, out, _, output = scene
    rec = pycolmap.Reconstruction(out / "sparse")
    sigmas = load_sigmas(dataset.rigs)
    decisions = {d["rig"]: d for d in json.loads((out / "summary.json").read_text())["calibration_decisions"]}
    assert sorted(decisions) == ["rig01", "rig02", "rig03"] and all(d["reason"] for d in decisions.values())
    for held in {d["held"] for d in decisions.values()}:
        assert f"calibration {'held at rigs.yaml' if held else 'refined'}: " in output
    for rig in load_rigs(dataset.rigs):
        narrow = rec.find_image_with_name(f"{rig.name}/narrow/frame0000.png")
        wide = rec.find_image_with_name(f"{rig.name}/wide/frame0000.png")
        np.testing.assert_allclose(rec.cameras[narrow.camera_id].params, rig.narrow.params, atol=1e-9)
        moved = (np.asarray(rec.cameras[wide.camera_id].params) - np.asarray(rig.wide.params)) / sigmas[rig.name].wide
        if decisions[rig.name]["held"]:
            assert np.all(moved == 0.0), moved
        else:
            assert np.all(np.abs(moved) < 3.0) and np.abs(moved).max() > 1e-3, moved
        composed = rig.narrow_from_wide * wide.cam_from_world()
        np.testing.assert_allclose(narrow.cam_from_world().matrix(), composed.matrix(), atol=1e-9)


def test_narrow_poses_file_is_consistent(scene):
    _, out, _, _ = scene
    data = json.loads((out / "narrow_poses.json").read_text())
    assert data["metric"] is True and len(data["narrow"]) == 3 and len(data["pairs"]) == 3
    poses = {n["name"]: n for n in data["narrow"]}
    rng = np.random.default_rng(0)
    for pair in data["pairs"]:
        pi, pj = poses[pair["i"]], poses[pair["j"]]
        ri, ti = np.array(pi["cam_from_world"]["rotation"]), np.array(pi["cam_from_world"]["translation"])
        rj, tj = np.array(pj["cam_from_world"]["rotation"]), np.array(pj["cam_from_world"]["translation"])
        rel = pair["narrow_j_from_narrow_i"]
        r_ji, t_ji = np.array(rel["rotation"]), np.array(rel["translation"])
        np.testing.assert_allclose(r_ji, rj @ ri.T, atol=1e-9)
        np.testing.assert_allclose(t_ji, tj - rj @ ri.T @ ti, atol=1e-9)
        e = pair["euler_zyx_deg"]
        np.testing.assert_allclose(rotation_from_euler_zyx_degrees(e["yaw"], e["pitch"], e["roll"]), r_ji, atol=1e-9)
        ci, cj = np.array(pi["centre"]), np.array(pj["centre"])
        assert pair["distance_m"] == pytest.approx(np.linalg.norm(cj - ci), abs=1e-9)
        np.testing.assert_allclose(np.array(pair["centre_direction_in_i"]) * pair["distance_m"], ri @ (cj - ci),
                                   atol=1e-9)
        # F_ji: points seen by camera i project (pinhole part) onto their epipolar lines in camera j.
        ki = np.array(pycolmap.Camera(**{k: pi["camera"][k] for k in ("model", "width", "height", "params")})
                      .calibration_matrix())
        kj = np.array(pycolmap.Camera(**{k: pj["camera"][k] for k in ("model", "width", "height", "params")})
                      .calibration_matrix())
        points_i = np.column_stack([rng.uniform(-1, 1, (50, 2)) * 0.1, rng.uniform(10, 30, 50)])
        points_i[:, :2] *= points_i[:, 2:]
        x_i = (ki @ points_i.T).T
        x_j = (kj @ (r_ji @ points_i.T + t_ji[:, None])).T
        x_i, x_j = x_i / x_i[:, 2:], x_j / x_j[:, 2:]
        f = np.array(pair["F_ji"])
        lines = (f @ x_i.T).T
        distances = np.abs(np.sum(lines * x_j, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)
        assert distances.max() < 1e-6


def test_points_open_in_open3d(scene):
    import open3d as o3d

    _, out, _, _ = scene
    cloud = o3d.io.read_point_cloud(str(out / "points3D.ply"))
    assert len(cloud.points) == pycolmap.Reconstruction(out / "sparse").num_points3D() > 500


def test_model_opens_in_debian_colmap(scene, tmp_path):
    _, out, _, _ = scene
    analysis = subprocess.run(["colmap", "model_analyzer", "--path", str(out / "sparse")],
                              capture_output=True, text=True, check=True)
    text = analysis.stdout + analysis.stderr
    assert "Registered images: 6" in text and "Cameras: 6" in text
    subprocess.run(["colmap", "model_converter", "--input_path", str(out / "sparse"), "--output_path",
                    str(tmp_path), "--output_type", "TXT"], capture_output=True, check=True)
    rows = [line.split() for line in (tmp_path / "images.txt").read_text().splitlines() if not line.startswith("#")]
    names = sorted(row[9] for row in rows if len(row) == 10)  # image rows; point rows have 3k fields
    assert names == sorted(f"rig0{i}/{s}/frame0000.png" for i in (1, 2, 3) for s in ("narrow", "wide"))


def test_rerun_refuses_to_overwrite_then_resumes(scene):
    dataset, out, args, _ = scene
    before = (out / "summary.json").read_text()
    refused = CliRunner().invoke(app, args)
    assert refused.exit_code == 1 and "--overwrite" in refused.output
    assert (out / "summary.json").read_text() == before
    with pycolmap.Database.open(out / "database.db") as db:
        keypoints_before = db.num_keypoints()
    again = CliRunner().invoke(app, args + ["--overwrite"])
    assert again.exit_code == 0, again.output
    with pycolmap.Database.open(out / "database.db") as db:
        assert db.num_keypoints() == keypoints_before
    assert "Features for 0 images: 0 extracted, 0 from the feature cache" in (out / "colmap.log").read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["registered"]["narrow"]["registered"] == 3


def test_changed_settings_recompute_instead_of_reusing_stale_work(scene, tmp_path):
    _, out, args, _ = scene
    work = tmp_path / "out"
    shutil.copytree(out, work)
    args = [a if a != str(out) else str(work) for a in args] + ["--overwrite"]
    with pycolmap.Database.open(work / "database.db") as db:
        keypoints, matches = db.num_keypoints(), db.num_matches()
    # A stricter ratio test: the features stay, the matches are recomputed (fewer of them).
    stricter = CliRunner().invoke(app, args + ["--max-ratio", "0.6"])
    assert stricter.exit_code == 0, stricter.output
    with pycolmap.Database.open(work / "database.db") as db:
        assert db.num_keypoints() == keypoints and 0 < db.num_matches() < 0.9 * matches  # measured 2387 vs 2885
    log = (work / "colmap.log").read_text()
    assert "max_ratio: 0.8 -> 0.6" in log and "recomputing its matches" in log
    assert json.loads((work / "features.json").read_text())["matching"]["max_ratio"] == 0.6
    # Another feature type: both are recomputed (ASIFT finds more points on these views).
    asift = CliRunner().invoke(app, args + ["--features", "asift"])
    assert asift.exit_code == 0, asift.output
    with pycolmap.Database.open(work / "database.db") as db:
        assert db.num_keypoints() > keypoints
    assert "type: sift -> asift" in (work / "colmap.log").read_text()


def test_a_distance_in_millimetres_is_named_after_mapping_nothing_adjusted(scene, tmp_path):
    """The scene's rig01-rig03 distance written 1000x too small: the run stops after mapping with one line naming
    it and the distance the bar gives (it ran the adjustment for minutes and finished with every observation off)."""
    import yaml

    dataset, out, args, _ = scene
    work = copy_run(out, tmp_path / "out")
    spec = yaml.safe_load(dataset.scale.read_text())
    true = spec["camera_distance"][0]["meters"]
    spec["camera_distance"][0]["meters"] = true / 1000
    scale = tmp_path / "scale.yaml"
    scale.write_text(yaml.safe_dump(spec))
    args = [str(scale) if a == str(dataset.scale) else str(work) if a == str(out) else a for a in args]
    before = (work / "summary.json").read_text()
    logged = len((work / "colmap.log").read_text())
    result = CliRunner().invoke(app, args + ["--overwrite"])
    assert result.exit_code == 1, result.output
    message = result.output.strip().splitlines()[-1]
    assert message.startswith(f"error: {scale}: camera_distance[0] ('rig01/wide' - 'rig03/wide', "), message
    assert "and known_length[0] (2 m) disagree on the scale by 1/" in message
    would = float(message.split("the first would be ")[1].split(" m")[0])
    assert abs(would - true) < 0.05 * true, (would, true)
    assert "Stage adjust" not in (work / "colmap.log").read_text()[logged:]
    assert (work / "summary.json").read_text() == before  # the earlier result is untouched
