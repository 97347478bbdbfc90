"""The calibration uncertainties: their pieces (left Jacobian, per-view noise, the rigs.yaml keys) and, on
rendered boards with exact ground truth, that errors / written sigmas have an RMS of ~1 per parameter group."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from rigsfm.calibrate.joint import left_jacobian, view_noise
from rigsfm.calibrate.uncertainty import RigSigmas, add_sigmas, colmap_param_sigmas, sigmas_from_entry
from rigsfm.core.errors import InputError


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
    back = sigmas_from_entry(entry, "rigs.yaml: rig rig01")
    np.testing.assert_allclose(back.wide, sigmas.wide, rtol=1e-3)
    np.testing.assert_allclose(back.rotation_deg, sigmas.rotation_deg, rtol=1e-3)
    np.testing.assert_allclose(back.covariance, cov, rtol=1e-7)
    assert sigmas_from_entry(_entry(), "x").wide is None  # all keys optional
    bad = yaml.safe_load(text)["rigs"][0]
    bad["sensors"]["narrow"]["sigmas"] = [0.1] * 7
    with pytest.raises(InputError, match="sensor narrow sigmas .one per entry of params"):
        sigmas_from_entry(bad, "rigs.yaml: rig rig01")
    bad = yaml.safe_load(text)["rigs"][0]
    bad["narrow_from_wide"]["covariance"][0][0] = -1e-8
    with pytest.raises(InputError, match="positive semi-definite"):
        sigmas_from_entry(bad, "rigs.yaml: rig rig01")


@pytest.mark.slow
def test_written_sigmas_are_honest(tmp_path):
    """Seeds 0..11 of benchmarks/calibration_sigmas.py (2 per setup: 24/16/12 common views, 4:1 and 3:1 rigs):
    per parameter group RMS(actual error / written sigma) within [0.7, 1.4]. 4-7 min on the shared 2-core
    machine, mostly rendering (calibration ~5 s per seed); the benchmark runs 24 seeds. Fewer seeds are too
    few: seeds 6..11 alone give 0.60 for the wide focal group."""
    from benchmarks.calibration_sigmas import HONEST, calibrate_and_compare, summary, table

    start = time.perf_counter()
    runs = [calibrate_and_compare(seed, tmp_path) for seed in range(12)]
    print(f"\n{table(runs)}\n{time.perf_counter() - start:.0f} s")
    for group, row in summary(runs).items():
        assert HONEST[0] <= row["rms_z"] <= HONEST[1], (group, row)
