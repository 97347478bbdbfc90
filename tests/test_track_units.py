"""rigsfm.track without images: verdicts on synthetic change series, the rig pose solver and its covariance."""

import dataclasses

import numpy as np
import pycolmap
import pytest

from rigsfm.core.conventions import rotation_vector
from rigsfm.track.options import RegistrationOptions, Thresholds
from rigsfm.track.pose import estimate_rig_pose, pose_covariance
from rigsfm.track.verdict import classify

DEG, MM = np.radians(1.0), 1e-3
SIGMA = np.diag([0.003 * DEG] * 3 + [1.0 * MM] * 3) ** 2  # a well-registered frame: 0.003 deg, 1 mm


def series(n, rng, jitter_deg=0.0, jitter_mm=0.0, noise=True):
    """n changes [w, d] (rad, m): estimation noise of SIGMA plus zero-mean jitter of the given size."""
    out = rng.multivariate_normal(np.zeros(6), SIGMA, n) if noise else np.zeros((n, 6))
    directions = rng.normal(size=(n, 6))
    directions[:, :3] /= np.linalg.norm(directions[:, :3], axis=1, keepdims=True)
    directions[:, 3:] /= np.linalg.norm(directions[:, 3:], axis=1, keepdims=True)
    return out + np.hstack([directions[:, :3] * jitter_deg * DEG, directions[:, 3:] * jitter_mm * MM])


def verdict(changes, covariance=SIGMA):
    frames = [f"f{i:03d}" for i in range(len(changes))]
    return classify(frames, changes, [covariance] * len(changes), covariance, Thresholds())


def test_still_rig_is_stable_and_never_flagged():
    rng = np.random.default_rng(0)
    for _ in range(20):
        v = verdict(series(12, rng))
        assert v.verdict == "stable" and not any(v.flagged) and v.steps == []


def test_zero_mean_shake_above_threshold_is_shaking_not_moved():
    rng = np.random.default_rng(1)
    for _ in range(20):
        v = verdict(series(12, rng, jitter_deg=0.1, jitter_mm=3.0))
        assert v.verdict == "shaking" and v.steps == []
        assert sum(v.flagged) >= 10


@pytest.mark.parametrize("at", [3, 6, 9])
def test_bump_is_a_step_at_the_right_frame(at):
    rng = np.random.default_rng(at)
    changes = series(12, rng, jitter_deg=0.02, jitter_mm=1.0)
    bump = np.r_[np.array([0.0, 0.2, 0.1]) * DEG, np.array([10.0, 0.0, -5.0]) * MM]
    changes[at:] += bump
    v = verdict(changes)
    assert v.verdict == "moved"
    assert [s.index for s in v.steps] == [at] and v.steps[0].frame == f"f{at:03d}"
    assert v.steps[0].rotation_deg == pytest.approx(np.degrees(np.linalg.norm(bump[:3])), abs=0.03)
    assert v.steps[0].translation_mm == pytest.approx(1000 * np.linalg.norm(bump[3:]), abs=3.0)
    assert v.flagged == [i >= at for i in range(12)]


@pytest.mark.parametrize("at", [1, 2])
def test_a_bump_after_the_first_frames_is_a_step_against_the_baseline(at):
    """A rig bumped at frame 2 of 5 (rendered: 0.3 deg, 20 mm, three frames flagged) was 'shaking', with no step:
    a step needed three frames before it, though one before the first frame needs none (the baseline)."""
    changes = series(6, np.random.default_rng(at))
    changes[at:] += np.r_[np.array([0.0, 0.2, 0.1]) * DEG, np.array([10.0, 0.0, -5.0]) * MM]
    v = verdict(changes)
    assert v.verdict == "moved" and [s.index for s in v.steps] == [at]


def test_moved_before_tracking_started_is_a_step_at_the_first_frame():
    changes = series(8, np.random.default_rng(3)) + np.r_[np.array([0.0, 0.0, 0.3]) * DEG, np.zeros(3)]
    v = verdict(changes)
    assert v.verdict == "moved" and [s.index for s in v.steps] == [0]


def test_a_bump_in_the_last_frames_is_not_yet_a_step():
    changes = series(10, np.random.default_rng(4))
    changes[8:, 2] += 0.3 * DEG
    v = verdict(changes)
    assert v.verdict == "shaking" and v.flagged == [False] * 8 + [True] * 2
    # ... but it is said: a rig moved just now would otherwise read 'shaking' at the moment it matters
    assert v.unsettled_frames == 2 and v.to_dict()["unsettled_frames"] == 2


def test_only_flags_at_the_end_after_still_frames_are_unsettled():
    """A shaking rig's flags come and go, so its last frame flagged says nothing; a still, a moved (three frames
    after its step) and a shaking series have no unsettled frames, a bump in the last frame of a still one has."""
    rng = np.random.default_rng(5)
    assert verdict(series(12, rng)).unsettled_frames == 0
    shaking = [verdict(series(12, rng, jitter_deg=0.1, jitter_mm=3.0)) for _ in range(10)]
    assert all(v.flagged[-1] and v.unsettled_frames == 0 for v in shaking if v.flagged[-1])
    assert any(v.flagged[-1] for v in shaking)
    changes = series(12, np.random.default_rng(6))
    changes[6:] += np.r_[np.array([0.0, 0.2, 0.1]) * DEG, np.array([10.0, 0.0, -5.0]) * MM]
    moved = verdict(changes)
    assert moved.verdict == "moved" and moved.unsettled_frames == 0
    still = series(12, np.random.default_rng(7))
    still[11:] += np.r_[np.array([0.0, 0.0, 0.4]) * DEG, np.zeros(3)]
    last = verdict(still)
    assert last.verdict == "shaking" and last.unsettled_frames == 1, last.flagged


def test_shift_within_the_weak_direction_is_not_flagged():
    """A wide camera seeing its map at one depth: 20 mm sideways with a compensating rotation is noise."""
    weak = np.r_[np.array([0.0, 0.03, 0.0]) * DEG, np.array([20.0, 0.0, 0.0]) * MM]
    weak /= np.linalg.norm(weak)
    covariance = SIGMA + (0.025 / np.linalg.norm(weak[3:])) ** 2 * np.outer(weak, weak)  # 25 mm sigma along it
    changes = np.array([s * 0.02 / np.linalg.norm(weak[3:]) * weak for s in (-1, 1, 0.5, -0.8, 1, -1)])
    v = verdict(changes, covariance)
    assert v.verdict == "stable" and not any(v.flagged)
    assert verdict(changes).verdict != "stable"  # the same numbers with a tight covariance would be flagged


def _projections(camera, cam_from_world, xyz):
    m = cam_from_world.matrix()
    return np.asarray(camera.img_from_cam(xyz @ m[:, :3].T + m[:, 3]))


def test_generalized_pose_with_fixed_esl_recovers_the_rig_pose():
    rng = np.random.default_rng(7)
    wide = pycolmap.Camera(model="PINHOLE", width=800, height=600, params=[450, 450, 400, 300])
    narrow = pycolmap.Camera(model="PINHOLE", width=800, height=600, params=[1800, 1800, 400, 300])
    narrow_from_wide = pycolmap.Rigid3d(pycolmap.Rotation3d(axis_angle=np.array([0.17, 0.0, 0.0])),
                                        np.array([-0.06, 0.0, 0.0]))
    truth = pycolmap.Rigid3d(pycolmap.Rotation3d(axis_angle=np.array([0.01, -0.3, 0.02])), np.array([1.0, -2.0, 0.5]))
    world_from_wide = truth.inverse().matrix()
    wide_pts = np.column_stack([rng.uniform(-15, 15, 300), rng.uniform(-8, 4, 300), rng.uniform(30, 44, 300)])
    narrow_dirs = np.column_stack([rng.uniform(-0.2, 0.2, 200), rng.uniform(-0.15, 0.15, 200), np.ones(200)])
    narrow_in_wide = narrow_from_wide.inverse().matrix()
    narrow_pts = (narrow_dirs * 15.0) @ narrow_in_wide[:, :3].T + narrow_in_wide[:, 3]

    def to_world(p):
        return p @ world_from_wide[:, :3].T + world_from_wide[:, 3]

    xyz = {"wide": to_world(wide_pts), "narrow": to_world(narrow_pts)}
    cameras = {"wide": wide, "narrow": narrow}
    sensor_from_rig = {"wide": pycolmap.Rigid3d(), "narrow": narrow_from_wide}
    correspondences = {s: (_projections(cameras[s], sensor_from_rig[s] * truth, xyz[s])
                           + rng.normal(0, 0.2, (len(xyz[s]), 2)), xyz[s]) for s in cameras}
    correspondences["narrow"][0][:20] += 50.0  # outliers
    pose, inliers, used = estimate_rig_pose(correspondences, cameras, sensor_from_rig, RegistrationOptions())
    assert used == ["wide", "narrow"] and inliers.sum() == 480 and not inliers[300:320].any()
    assert np.degrees(pose.rotation.angle_to(truth.rotation)) < 0.005
    assert np.linalg.norm(pose.inverse().translation - truth.inverse().translation) < 0.01
    only_narrow = {"narrow": correspondences["narrow"]}
    pose_n, _, used_n = estimate_rig_pose(only_narrow, cameras, sensor_from_rig, RegistrationOptions())
    # Narrow field of view: weaker, but through E^sl in the rig frame (a wrong E^sl would be ~10 deg off).
    assert used_n == ["narrow"] and np.degrees(pose_n.rotation.angle_to(truth.rotation)) < 0.1


def test_pose_covariance_matches_monte_carlo():
    rng = np.random.default_rng(0)
    camera = pycolmap.Camera(model="PINHOLE", width=800, height=600, params=[450, 450, 400, 300])
    xyz = np.column_stack([rng.uniform(-15, 15, 300), rng.uniform(-8, 4, 300), rng.uniform(38, 44, 300)])
    exact = _projections(camera, pycolmap.Rigid3d(), xyz)
    samples = []
    for _ in range(80):
        xy = exact + rng.normal(0, 0.2, exact.shape)
        pose, _, _ = estimate_rig_pose({"wide": (xy, xyz)}, {"wide": camera}, {"wide": pycolmap.Rigid3d()},
                                       RegistrationOptions())
        samples.append(np.r_[rotation_vector(pose.rotation), pose.inverse().translation])
    empirical = np.sqrt(np.diag(np.cov(np.array(samples).T)))
    predicted = np.sqrt(np.diag(pose_covariance(pose, [(camera, pycolmap.Rigid3d(), xy, xyz)], np.eye(3))))
    np.testing.assert_allclose(predicted, empirical, rtol=0.3)
    assert predicted[3:].max() > 0.005  # the weak sideways shift: centimetres, though 0.2 px noise


def test_new_images_with_a_rig_lacking_a_frame_warn_as_a_run_does(tmp_path, caplog):
    """rigsfm track said nothing where one rig's frame was misnamed or lost in NEW_IMAGES; now the run's warning."""
    import logging
    import shutil
    from types import SimpleNamespace

    from test_bad_input import make_inputs

    from rigsfm.core.rig import load_rigs
    from rigsfm.track.pipeline import frame_tasks

    images, rigs_path, _ = make_inputs(tmp_path, rigs=("rig01", "rig02", "rig03"))
    for rig in ("rig01", "rig02", "rig03"):
        for sensor in ("wide", "narrow"):
            shutil.copy(images / rig / sensor / "f0.png", images / rig / sensor / "f1.png")
    reference = SimpleNamespace(rigs={r.name: SimpleNamespace(wide=r.wide, narrow=r.narrow,
                                                              narrow_from_wide=r.narrow_from_wide)
                                      for r in load_rigs(rigs_path)}, sparse="sparse")
    with caplog.at_level(logging.WARNING):
        assert len(frame_tasks(images, reference)) == 6  # type: ignore[arg-type]
    assert "MISSING FRAMES" not in caplog.text
    for sensor in ("wide", "narrow"):
        (images / "rig03" / sensor / "f1.png").unlink()
    with caplog.at_level(logging.WARNING):
        assert len(frame_tasks(images, reference)) == 5  # type: ignore[arg-type]
    assert [r.getMessage() for r in caplog.records] == [
        "MISSING FRAMES: 1 of 3 rigs lack frames other rigs have ('rig03' lacks 'f1.png'; 2 frames in all): a rig "
        "adds no view at a frame it lacks; check for a file misnamed or not copied"], caplog.text


def test_tracking_a_result_without_scale_warns_that_its_millimetres_are_not(tmp_path, caplog):
    """rigsfm track on a run without scale printed shifts and compared its threshold in 'mm' without a word."""
    import json
    import logging

    from rigsfm.core.workspace import Workspace
    from rigsfm.track.pipeline import warn_not_metric

    for metric in (True, False):
        (tmp_path / "summary.json").write_text(json.dumps({"metric": metric}))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            warn_not_metric(Workspace(tmp_path))
        assert ("NOT METRIC" in caplog.text) is (not metric), caplog.text


def test_the_report_says_the_tracking_millimetres_are_not_on_a_result_without_scale(tmp_path):
    """report.html's tracking section gave a run without scale its thresholds and shifts in mm without a word."""
    import json

    from rigsfm.track.report import track_report_section

    _tracked_against(tmp_path, b"model")
    for metric in (True, False):
        (tmp_path / "summary.json").write_text(json.dumps({"metric": metric}))
        assert ("Not metric" in track_report_section(tmp_path)) is (not metric)


def _tracked_against(out, model: bytes | None):
    """OUT with a model (sparse/) and a tracking series made against it."""
    import json

    from rigsfm.core.workspace import Workspace, model_fingerprint

    workspace = Workspace(out)
    if model is not None:  # None: OUT/sparse as it is
        workspace.sparse.mkdir(parents=True)
        (workspace.sparse / "images.bin").write_bytes(model)
    workspace.track.root.mkdir(parents=True)
    rig = {"frames": [{"frame": "f0.png", "status": "registered"}],
           "verdict": {"verdict": "stable", "steps": [], "flagged_frames": 0, "jitter_rotation_deg": 0.001,
                       "jitter_translation_mm": 0.1}}
    workspace.track.poses_json.write_text(json.dumps({
        "reference": {"sparse": str(workspace.sparse), "fingerprint": model_fingerprint(workspace.sparse)},
        "thresholds": {"rotation_deg": 0.05, "translation_mm": 5.0, "significance_chi2": 16.27},
        "rigs": {"rig01": rig}}))
    return workspace


def test_the_report_hashes_the_model_once_for_its_tracking_and_persons(tmp_path, monkeypatch):
    """report.html's tracking and persons sections each read every file of OUT/sparse to compare their results'
    model with this one: the page hashed the model twice."""
    import json

    from test_camera_files import finished_workspace

    import rigsfm.associate.report
    import rigsfm.inspect.report.html
    import rigsfm.track.report
    from rigsfm.core import workspace as workspace_module
    from rigsfm.inspect.report.write import write_report

    finished_workspace(tmp_path)
    workspace = _tracked_against(tmp_path, None)
    (workspace.associate / "frame0000").mkdir(parents=True)
    (workspace.associate / "frame0000" / "persons.json").write_text(
        json.dumps({"frame": "frame0000.png", "views": [], "persons": [], "unassigned": []}))
    (workspace.associate / ".rigsfm-associate.json").write_text(json.dumps(
        {"written_by": "rigsfm associate", "model": workspace_module.model_fingerprint(workspace.sparse)}))
    hashed = []

    def counted(sparse):
        hashed.append(sparse)
        return workspace_module.model_fingerprint(sparse)

    for module in (rigsfm.inspect.report.html, rigsfm.track.report, rigsfm.associate.report):
        monkeypatch.setattr(module, "model_fingerprint", counted, raising=False)  # the page had none of its own
    page = write_report(tmp_path).read_text()
    assert "stable" in page and "<td>frame0000.png</td>" in page  # both sections shown: the same model
    assert len(hashed) == 1, hashed


def test_the_report_does_not_show_the_tracking_of_a_replaced_result(tmp_path):
    """After `rigsfm run --overwrite` on a new recording, report.html showed OUT/track's verdicts, made against the
    replaced model (rigs since moved read 'stable'), as this result's; `rigsfm track` itself refuses that series."""
    from rigsfm.track.report import track_report_section

    workspace = _tracked_against(tmp_path, b"the model tracked against")
    assert "stable" in track_report_section(tmp_path)
    (workspace.sparse / "images.bin").write_bytes(b"the model of a run --overwrite")
    section = track_report_section(tmp_path)
    assert "stable" not in section and "earlier result" in section and "--overwrite" in section


def test_a_moved_rig_is_said_with_what_no_longer_holds():
    """A rig's verdict 'moved' was a word in the table: nothing said that the run's poses, F_ji and bands of that
    rig, its exports and `associate --poses-from`, no longer hold after the step, nor what to do."""
    from rigsfm.track.pipeline import moved_warning

    rng = np.random.default_rng(6)
    still = verdict(series(12, rng))
    changes = series(12, rng)
    changes[6:] += np.r_[np.array([0.0, 0.2, 0.1]) * DEG, np.array([10.0, 0.0, -5.0]) * MM]
    moved = verdict(changes)
    assert moved.verdict == "moved"
    assert moved_warning({"rigs": {"rig01": {"verdict": still.to_dict()}}}, "out") is None
    warning = moved_warning({"rigs": {"rig01": {"verdict": still.to_dict()}, "rig03": {"verdict": moved.to_dict()}}},
                            "out")
    step = moved.to_dict()["steps"][0]
    assert warning is not None and warning.startswith(
        f"MOVED: rig03 at f006 ({step['rotation_deg']:.3f} deg, {step['translation_mm']:.1f} mm). The poses of out ")
    assert "rig01" not in warning and "`rigsfm run IMAGES --rigs rigs.yaml --out NEW_OUT`" in warning


def test_a_new_series_leaves_no_plot_of_a_rig_it_does_not_hold(tmp_path):
    """`track --overwrite` with a recording of fewer rigs left plots/<rig>.png of the discarded series (a rig03
    'moved' plot beside a series without rig03); the user's own files in plots/ are kept."""
    from rigsfm.core.workspace import TrackPaths
    from rigsfm.track.options import Thresholds
    from rigsfm.track.pipeline import _save

    paths = TrackPaths(tmp_path / "track")
    paths.plots.mkdir(parents=True)
    paths.plot("rig03").write_bytes(b"the discarded series' plot")
    (paths.plots / "notes.png").write_bytes(b"the user's")
    _save(paths, {"thresholds": dataclasses.asdict(Thresholds()), "rigs": {}}, plots=True, rigs=["rig01", "rig03"])
    assert sorted(p.name for p in paths.plots.iterdir()) == ["notes.png"]
    assert paths.poses_json.is_file() and paths.poses_csv.is_file()
