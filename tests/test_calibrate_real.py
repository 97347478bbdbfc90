"""rigsfm calibrate on OpenCV's real stereo chessboard pairs, checked against OpenCV run directly."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from support import REAL_STEREO

from rigsfm.calibrate import CalibrateOptions, CalibrationResult, calibrate, calibrate_rigs, write_calibration
from rigsfm.calibrate.board import board_spec_from_dict
from rigsfm.core.rig import load_rigs

DATA = REAL_STEREO
FRAMES = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]
SPEC = {"type": "chessboard", "inner_corners": [9, 6], "square": 0.025}



@pytest.fixture(scope="module")
def board_dir(tmp_path_factory) -> Path:
    """BOARD/rig01/{wide,narrow}/NN.jpg from leftNN.jpg (wide) / rightNN.jpg (narrow)."""
    root = tmp_path_factory.mktemp("real") / "BOARD"
    for sensor, side in (("wide", "left"), ("narrow", "right")):
        (root / "rig01" / sensor).mkdir(parents=True)
        for n in FRAMES:
            shutil.copy(DATA / f"{side}{n}.jpg", root / "rig01" / sensor / f"{n}.jpg")
    return root


def opencv_corners(path: Path, win: int | None) -> np.ndarray:
    """OpenCV's own detection; ``win=None``: half-window 0.4 x corner spacing (clipped to 3..11)."""
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    found, corners = cv2.findChessboardCorners(gray, (9, 6), cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    assert found, path
    if win is None:
        grid = corners.reshape(6, 9, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(), np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
        win = int(np.clip(round(0.4 * spacing), 3, 11))
    return cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01))


def object_points() -> np.ndarray:
    objp = np.zeros((54, 3), np.float32)
    objp[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    return objp


@pytest.fixture(scope="module")
def result(board_dir):
    return calibrate_rigs(board_dir, board_spec_from_dict(SPEC), distortion="opencv").rigs[0]


def test_matches_opencv_on_the_same_views(result):
    """Same corners, same views, same model: our intrinsics and E^sl equal OpenCV's to numerical precision."""
    size = (640, 480)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    ref = {}
    for cam, side in ((result.wide, "left"), (result.narrow, "right")):
        views = cam.used_views
        img = [opencv_corners(DATA / f"{side}{n}.jpg", None) for n in views]
        rms, K, dist, _, _ = cv2.calibrateCamera([object_points()] * len(views), img, size, None, None,
                                                 flags=cv2.CALIB_FIX_K3, criteria=crit)
        ref[side] = (K, dist)
        assert cam.rms == pytest.approx(rms, abs=1e-4)
        np.testing.assert_allclose(cam.K, K, rtol=1e-5, atol=1e-3)
        camera = cam.colmap_camera()
        assert camera.principal_point_x == pytest.approx(K[0, 2] + 0.5, abs=1e-3)  # COLMAP convention
    common = result.stereo.views
    out = cv2.stereoCalibrate([object_points()] * len(common), [opencv_corners(DATA / f"left{n}.jpg", None) for n in common],
                              [opencv_corners(DATA / f"right{n}.jpg", None) for n in common], *ref["left"], *ref["right"],
                              size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    fixed = result.stereo.fixed
    assert fixed.rms == pytest.approx(out[0], abs=1e-4)
    np.testing.assert_allclose(fixed.T, out[6].ravel(), atol=1e-5)
    np.testing.assert_allclose(fixed.R, out[5], atol=1e-6)
    print(f"\nreal, same views: ours f_w={result.wide.K[0, 0]:.3f} pp_w=({result.wide.K[0, 2]:.3f},{result.wide.K[1, 2]:.3f}) "
          f"f_n={result.narrow.K[0, 0]:.3f} pp_n=({result.narrow.K[0, 2]:.3f},{result.narrow.K[1, 2]:.3f}) "
          f"rms {result.wide.rms:.4f}/{result.narrow.rms:.4f} stereo {fixed.rms:.4f} baseline {1000 * fixed.baseline:.3f} mm; "
          f"OpenCV f_w={ref['left'][0][0, 0]:.3f} f_n={ref['right'][0][0, 0]:.3f} stereo {out[0]:.4f} "
          f"baseline {1000 * np.linalg.norm(out[6]):.3f} mm")


def test_close_to_opencv_sample_pipeline(result):
    """OpenCV's stereo_calib sample recipe (all 13 pairs, 11x11 subpixel window, k3 free, joint stereo):
    a different corner refinement and view set, so agreement is to ~1 %, not to numerical precision."""
    size = (640, 480)
    obj = [object_points()] * len(FRAMES)
    left = [opencv_corners(DATA / f"left{n}.jpg", 11) for n in FRAMES]
    right = [opencv_corners(DATA / f"right{n}.jpg", 11) for n in FRAMES]
    rms_l, K_l, d_l, _, _ = cv2.calibrateCamera(obj, left, size, None, None)
    rms_r, K_r, d_r, _, _ = cv2.calibrateCamera(obj, right, size, None, None)
    rms_s, *_, _R, T, _, _ = cv2.stereoCalibrate(obj, left, right, K_l, d_l, K_r, d_r, size, flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    final = result.stereo.final
    print(f"\nOpenCV sample recipe: f_l={K_l[0, 0]:.3f} pp_l=({K_l[0, 2]:.3f},{K_l[1, 2]:.3f}) rms {rms_l:.4f}; "
          f"f_r={K_r[0, 0]:.3f} pp_r=({K_r[0, 2]:.3f},{K_r[1, 2]:.3f}) rms {rms_r:.4f}; stereo rms {rms_s:.4f} "
          f"baseline {1000 * np.linalg.norm(T):.3f} mm | ours (final, joint={result.stereo.use_joint}): "
          f"f_w={final.K_wide[0, 0]:.3f} f_n={final.K_narrow[0, 0]:.3f} baseline {1000 * final.baseline:.3f} mm")
    assert final.K_wide[0, 0] == pytest.approx(K_l[0, 0], rel=0.01)
    assert final.K_narrow[0, 0] == pytest.approx(K_r[0, 0], rel=0.01)
    assert abs(final.K_wide[0, 2] - K_l[0, 2]) < 3 and abs(final.K_narrow[1, 2] - K_r[1, 2]) < 6
    assert final.baseline == pytest.approx(np.linalg.norm(T), rel=0.01)
    # physically plausible: a horizontal stereo rig about 8 cm wide, cameras nearly parallel
    assert 0.07 < final.baseline < 0.10
    assert abs(final.T[0]) / final.baseline > 0.99
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(final.R)[0])) < 2.0
    assert result.wide.rms < 0.5 and result.narrow.rms < 0.5


def test_cli_writes_rigs_yaml_and_report(board_dir, tmp_path):
    board = tmp_path / "board.yaml"
    board.write_text(yaml.safe_dump(SPEC))
    out = tmp_path / "rigs.yaml"
    calibrate(board_dir, out, CalibrateOptions(board=board))
    (rig,) = load_rigs(out)
    assert rig.name == "rig01" and rig.wide.width == 640 and rig.wide.model.name in ("OPENCV", "FULL_OPENCV")
    assert 0.07 < np.linalg.norm(rig.narrow_from_wide.translation) < 0.10
    report = tmp_path / "rigs.calibration" / "rig01"
    for name in ("report.txt", "wide_view_errors.png", "narrow_coverage.png", "stereo_view_errors.png"):
        assert (report / name).is_file(), name
    assert cv2.imread(str(report / "wide_view_errors.png")) is not None
    assert "E^sl" in (report / "report.txt").read_text()


def test_an_out_named_json_is_written_as_json(result, tmp_path):
    """rigs.yaml may be JSON (docs/inputs.md): `--out rigs.json` gives a file other tools' JSON readers read."""
    out = tmp_path / "rigs.json"
    write_calibration(CalibrationResult(board_spec_from_dict(SPEC), [result]), out)
    data = json.loads(out.read_text())
    assert data["units"] == "meters" and data["rigs"][0]["name"] == "rig01"
    assert "sigma_rotation_deg" in data["rigs"][0]["narrow_from_wide"]
    (rig,) = load_rigs(out)
    assert 0.07 < np.linalg.norm(rig.narrow_from_wide.translation) < 0.10


def _parameters(rig, R0: np.ndarray) -> np.ndarray:
    """fx fy cx cy of both cameras (px), E^sl w (deg, R = Exp(w) R0) and t (mm): what the sigmas are compared on."""
    f = rig.stereo.final
    w = Rotation.from_matrix(rig.R @ R0.T).as_rotvec()
    return np.concatenate([[f.K_wide[0, 0], f.K_wide[1, 1], f.K_wide[0, 2], f.K_wide[1, 2], f.K_narrow[0, 0],
                            f.K_narrow[1, 1], f.K_narrow[0, 2], f.K_narrow[1, 2]], np.degrees(w), 1000 * rig.T])


def _jackknife(samples: np.ndarray) -> np.ndarray:
    k = len(samples)
    return np.sqrt((k - 1) / k * ((samples - samples.mean(0)) ** 2).sum(0))


@pytest.mark.slow  # 13 leave-one-pair-out calibrations
def test_sigmas_match_the_leave_one_pair_out_spread(result, tmp_path):
    """The written sigmas against the jackknife spread of the calibration over the 13 leave-one-pair-out runs
    (ours, and OpenCV's stereo_calib recipe for scale). Corner errors on these real images are correlated
    (neighbouring corners' residuals 0.3-0.5), so the independent-error covariance alone is ~2x too small here;
    the written (jackknife-inflated) sigmas must be within a factor 2 of the spread per group. ~15 s."""
    sigmas = result.sigmas()
    detail = result.stereo.joint_detail
    written = np.concatenate([sigmas.wide[:4], sigmas.narrow[:4], sigmas.rotation_deg, 1000 * sigmas.translation_m])
    iid = np.sqrt(np.diag(detail.covariance_iid))
    iid = np.concatenate([iid[:4], iid[detail.n_wide:detail.n_wide + 4], np.degrees(iid[-6:-3]), 1000 * iid[-3:]])
    ours = []
    for left_out in FRAMES:
        root = tmp_path / left_out / "BOARD"
        for sensor, side in (("wide", "left"), ("narrow", "right")):
            (root / "rig01" / sensor).mkdir(parents=True)
            for n in FRAMES:
                if n != left_out:
                    shutil.copy(DATA / f"{side}{n}.jpg", root / "rig01" / sensor / f"{n}.jpg")
        ours.append(_parameters(calibrate_rigs(root, board_spec_from_dict(SPEC), distortion="opencv").rigs[0], result.R))
    spread = _jackknife(np.array(ours))
    size, crit = (640, 480), (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    left = {n: opencv_corners(DATA / f"left{n}.jpg", 11) for n in FRAMES}
    right = {n: opencv_corners(DATA / f"right{n}.jpg", 11) for n in FRAMES}
    opencv = []
    for left_out in FRAMES:
        names = [n for n in FRAMES if n != left_out]
        obj, img_l, img_r = [object_points()] * len(names), [left[n] for n in names], [right[n] for n in names]
        _, K_l, d_l, _, _ = cv2.calibrateCamera(obj, img_l, size, None, None, flags=cv2.CALIB_FIX_K3, criteria=crit)
        _, K_r, d_r, _, _ = cv2.calibrateCamera(obj, img_r, size, None, None, flags=cv2.CALIB_FIX_K3, criteria=crit)
        _, K1, _, K2, _, R, T, _, _ = cv2.stereoCalibrate(obj, img_l, img_r, K_l, d_l, K_r, d_r, size, criteria=crit,
                                                          flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3)
        opencv.append(np.concatenate([[K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2], K2[0, 0], K2[1, 1], K2[0, 2], K2[1, 2]],
                                      np.degrees(Rotation.from_matrix(R @ result.R.T).as_rotvec()), 1000 * T.ravel()]))
    spread_opencv = _jackknife(np.array(opencv))
    names = [f"{c} {p}" for c in ("wide", "narrow") for p in ("fx", "fy", "cx", "cy")] + \
        ["E^sl w_x deg", "E^sl w_y deg", "E^sl w_z deg", "E^sl t_x mm", "E^sl t_y mm", "E^sl t_z mm"]
    print(f"\nsigma inflation (wide / narrow / E^sl) {' / '.join(f'{v:.2f}' for v in detail.inflation)}")
    print(f"{'':14}{'written':>9}{'iid':>9}{'spread':>9}{'OpenCV':>9}   (spread: jackknife over 13 leave-one-pair-out runs)")
    for i, n in enumerate(names):
        print(f"{n:14}{written[i]:9.4f}{iid[i]:9.4f}{spread[i]:9.4f}{spread_opencv[i]:9.4f}")
    groups = {"wide intrinsics": slice(0, 4), "narrow intrinsics": slice(4, 8), "E^sl rotation": slice(8, 11),
              "E^sl translation": slice(11, 14)}
    for group, cut in groups.items():
        ratio = np.sqrt(np.mean(written[cut] ** 2) / np.mean(spread[cut] ** 2))
        print(f"{group}: written / spread {ratio:.2f}, independent-error / spread "
              f"{np.sqrt(np.mean(iid[cut] ** 2) / np.mean(spread[cut] ** 2)):.2f}")
        assert 0.5 < ratio < 2.0, group


def test_readme_calibrate_command(tmp_path):
    """The README's `rigsfm calibrate` example, run as written (from a copy of the repository's data: it writes
    beside its --out), gives what the README says it prints and writes."""
    import os
    import re
    import shlex
    import subprocess
    import sys

    readme = (DATA.parents[2] / "README.md").read_text()
    command = re.search(r"```bash\n(\.venv/bin/rigsfm calibrate [^\n]*)\n```", readme).group(1)
    argv = shlex.split(command)
    assert argv[:3] == [".venv/bin/rigsfm", "calibrate", "tests/data/opencv-stereo/board"]
    shutil.copytree(DATA, tmp_path / "tests" / "data" / "opencv-stereo")  # the board/ layout's links resolved
    done = subprocess.run([sys.executable, "-m", "rigsfm", *argv[1:]], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300, env={**os.environ, "COLUMNS": "200"})
    assert done.returncode == 0, done.stdout + done.stderr
    printed = re.search(r"It prints a line per rig \(`(.*?)`\)", readme, re.S).group(1)
    assert " ".join(printed.split()) in done.stdout, done.stdout
    out = tmp_path / "out" / "calibration"
    rig = yaml.safe_load((out / "rigs.yaml").read_text())["rigs"][0]
    assert rig["name"] == "rig01" and len(rig["sensors"]["wide"]["sigmas"]) == 8
    assert "E^sl rotation sigma (deg, R_true = Exp(w) R, w in narrow axes): 0.0894 0.1023 0.0100" in \
        (out / "rigs.calibration" / "rig01" / "report.txt").read_text()
    assert "0.0894 0.1023 0.0100" in readme and (out / "rigs.calibration" / "summary.txt").is_file()
