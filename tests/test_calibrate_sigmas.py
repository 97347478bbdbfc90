"""The calibration uncertainties: their pieces (left Jacobian, per-view noise, the rigs.yaml keys) and, on
rendered boards with exact ground truth, that errors / written sigmas have an RMS of ~1 per parameter group."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pyceres
import pytest
import yaml
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rigsfm.calibrate.joint import _float64, _JointProblem, dense_residuals, left_jacobian, view_noise
from rigsfm.calibrate.uncertainty import RigSigmas, add_sigmas, colmap_param_sigmas, sigmas_from_entry
from rigsfm.core.errors import InputError
from rigsfm.synth.boards import board_views, default_hybrid_rig


def test_left_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for r in (rng.normal(0, 0.03, 3), rng.normal(0, 1.0, 3), np.array([0.0, 0.0, 1e-10])):
        R = cv2.Rodrigues(r)[0]
        numeric = np.empty((3, 3))
        for k in range(3):  # scipy's Log: cv2.Rodrigues returns 0 for angles below 1e-5 rad
            dr = np.zeros(3)
            dr[k] = 1e-6
            numeric[:, k] = (Rotation.from_matrix(cv2.Rodrigues(r + dr)[0] @ R.T).as_rotvec()
                             - Rotation.from_matrix(cv2.Rodrigues(r - dr)[0] @ R.T).as_rotvec()) / 2e-6
        np.testing.assert_allclose(left_jacobian(r), numeric, atol=1e-8)


def test_view_noise_recovers_each_views_noise():
    """A linear least-squares problem with shared and per-view unknowns and 10x different noise per view."""
    rng = np.random.default_rng(1)
    truth = np.array([0.02, 0.05, 0.1, 0.2, 0.04, 0.08])
    rows, shared = 120, 5
    J = np.zeros((rows * len(truth), shared + len(truth)))
    view_of_row = np.repeat(np.arange(len(truth)), rows)
    J[:, :shared] = rng.normal(size=(len(J), shared))
    J[np.arange(len(J)), shared + view_of_row] = 1.0
    residuals_true = rng.normal(size=len(J)) * truth[view_of_row]
    weights = 1 / truth[view_of_row]  # the fit's weights once the noise levels have settled
    Jw = weights[:, None] * J
    dx = np.linalg.lstsq(Jw, weights * residuals_true, rcond=None)[0]
    residuals = residuals_true - J @ dx  # residuals of the weighted fit
    noise, cameras = view_noise(residuals, Jw, view_of_row, np.array([0, 0, 0, 1, 1, 1]))
    np.testing.assert_allclose(noise, truth, rtol=0.2)
    assert cameras.shape == (2,)


def test_joint_problem_ends_at_the_float64_minimum_of_scipys_lm():
    """The joint refinement's Ceres problem (Schur complement on the board poses) ends where scipy's MINPACK
    Levenberg-Marquardt ends on the same weighted problem: exact projections of an 11x8 board, 0.1 px noise,
    float32 corners as detection gives them, 8 stereo and 4 wide-only views, a perturbed start."""
    rng = np.random.default_rng(3)
    rig = default_hybrid_rig()
    grid = np.mgrid[0:11, 0:8].T.reshape(-1, 2) * 0.06 - [0.3, 0.21]
    obj = np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)
    blocks, poses = [], []
    for i, (R, t) in enumerate(board_views(rng, 8, 4)):
        rvec = cv2.Rodrigues(R)[0].ravel()
        poses.append(np.concatenate([rvec, t]))
        views = [(0, rig.wide, R, t)] + ([(1, rig.narrow, rig.R @ R, rig.R @ t + rig.t)] if i < 8 else [])
        for cam, camera, Rc, tc in views:
            img = cv2.projectPoints(obj.astype(np.float64), cv2.Rodrigues(Rc)[0], tc, camera.K, camera.dist)[0]
            img = img.reshape(-1, 2) + rng.normal(0, 0.1, (len(obj), 2))
            inside = np.all((img > 0) & (img < camera.size), axis=1)
            assert inside.sum() >= 12
            blocks.append((cam, i, f"{i:03d}", *_float64((obj[inside], img[inside].astype(np.float32)))))
    intrinsics = [np.concatenate([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]], c.dist[:4]])
                  for c in (rig.wide, rig.narrow)]
    truth = np.concatenate([*intrinsics, cv2.Rodrigues(rig.R)[0].ravel(), rig.t, *poses])
    x0 = truth * (1 + rng.normal(0, 1e-3, len(truth))) + rng.normal(0, 1e-4, len(truth))
    weights = rng.uniform(5, 20, len(blocks))
    row_weights = np.repeat(weights, [2 * len(b[3]) for b in blocks])

    def weighted(x, jacobian: bool):
        residuals, J = dense_residuals(x, blocks, 8, 8)
        return row_weights[:, None] * J if jacobian else row_weights * residuals

    reference = least_squares(lambda x: weighted(x, False), x0, jac=lambda x: weighted(x, True), method="lm",
                              x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=500).x
    x, summary = _JointProblem(x0, blocks, 8, 8).solve(weights)
    assert summary.termination_type == pyceres.TerminationType.CONVERGENCE
    assert np.sum(weighted(x, False) ** 2) <= np.sum(weighted(reference, False) ** 2) * (1 + 1e-9)
    np.testing.assert_allclose(x[:4], reference[:4], atol=1e-5)  # wide fx, fy, cx, cy (px)
    np.testing.assert_allclose(x[8:12], reference[8:12], atol=1e-4)  # narrow
    np.testing.assert_allclose(x[16:], reference[16:], atol=1e-8)  # E^sl and board poses (rad, m)
    assert np.abs(x[:4] - truth[:4]).max() < 1.0  # and it is the right minimum


def test_colmap_param_sigmas_pad_full_opencv():
    cov = np.diag(np.arange(1.0, 10.0) ** 2)
    np.testing.assert_allclose(colmap_param_sigmas(cov, "FULL_OPENCV"), [1, 2, 3, 4, 5, 6, 7, 8, 9, 0, 0, 0])
    np.testing.assert_allclose(colmap_param_sigmas(cov[:8, :8], "OPENCV"), [1, 2, 3, 4, 5, 6, 7, 8])


def _entry() -> dict:
    camera = {"model": "OPENCV", "width": 960, "height": 720, "params": [640.0, 640.0, 480.5, 360.5, -0.1, 0.03, 0, 0]}
    return {"name": "rig01", "sensors": {"wide": dict(camera), "narrow": dict(camera)},
            "narrow_from_wide": {"rotation": np.eye(3).tolist(), "translation": [-0.12, 0.0, 0.0]}}


def test_sigma_keys_round_trip_and_are_checked():
    A = np.random.default_rng(2).normal(size=(6, 6))
    cov = A @ A.T * 1e-8
    sigmas = RigSigmas(wide=np.array([0.05, 0.05, 0.1, 0.08, 1.5e-4, 2.2e-4, 3e-5, 3e-5]), narrow=np.full(8, 0.3),
                       rotation_deg=np.degrees(np.sqrt(np.diag(cov)[:3])), translation_m=np.sqrt(np.diag(cov)[3:]),
                       covariance=cov)
    text = yaml.safe_dump({"rigs": [add_sigmas(_entry(), sigmas)]}, sort_keys=False, default_flow_style=None)
    entry = yaml.safe_load(text)["rigs"][0]
    assert list(entry["narrow_from_wide"]) == ["rotation", "translation", "sigma_rotation_deg", "sigma_translation_m",
                                               "covariance"]
    back = sigmas_from_entry(entry, "rigs.yaml: rig 'rig01'")
    np.testing.assert_allclose(back.wide, sigmas.wide, rtol=1e-3)
    np.testing.assert_allclose(back.rotation_deg, sigmas.rotation_deg, rtol=1e-3)
    np.testing.assert_allclose(back.covariance, cov, rtol=1e-7)
    assert sigmas_from_entry(_entry(), "x").wide is None  # all keys optional
    bad = yaml.safe_load(text)["rigs"][0]
    bad["sensors"]["narrow"]["sigmas"] = [0.1] * 7
    with pytest.raises(InputError, match="sensor narrow sigmas .one per entry of params"):
        sigmas_from_entry(bad, "rigs.yaml: rig 'rig01'")
    bad = yaml.safe_load(text)["rigs"][0]
    bad["narrow_from_wide"]["covariance"][0][0] = -1e-8
    with pytest.raises(InputError, match="positive semi-definite"):
        sigmas_from_entry(bad, "rigs.yaml: rig 'rig01'")
    # a large negative variance (the fuzz test's find): scaled by its clipped root it overflowed into numpy's
    # "Eigenvalues did not converge"
    bad["narrow_from_wide"]["covariance"][1][1] = -179769314.0
    with pytest.raises(InputError, match="positive semi-definite"):
        sigmas_from_entry(bad, "rigs.yaml: rig 'rig01'")
    bad = yaml.safe_load(text)["rigs"][0]
    bad["narrow_from_wide"]["covariance"][0][0] = 0.0  # no variance, yet a covariance with the others
    with pytest.raises(InputError, match="positive semi-definite"):
        sigmas_from_entry(bad, "rigs.yaml: rig 'rig01'")


@pytest.mark.slow
def test_written_sigmas_are_honest(tmp_path):
    """Seeds 0..11 of benchmarks/calibration_sigmas.py (2 per setup: 24/16/12 common views, 4:1 and 3:1 rigs):
    per parameter group RMS(actual error / written sigma) within [0.7, 1.4]. ~90 s alone on the 2-core
    machine, mostly rendering (calibration ~3.4 s per seed); the benchmark runs 24 seeds. Fewer seeds are too
    few: seeds 6..11 alone give 0.60 for the wide focal group."""
    from benchmarks.calibration_sigmas import HONEST, calibrate_and_compare, summary, table

    start = time.perf_counter()
    runs = [calibrate_and_compare(seed, tmp_path) for seed in range(12)]
    print(f"\n{table(runs)}\n{time.perf_counter() - start:.0f} s")
    for group, row in summary(runs).items():
        assert HONEST[0] <= row["rms_z"] <= HONEST[1], (group, row)
