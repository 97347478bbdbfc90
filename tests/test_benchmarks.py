"""Smoke test of the benchmark baselines on a tiny rendered scene, against the exact ground truth."""

import json
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.baselines.paper import PairResult, relative_scale, run_paper
from benchmarks.baselines.plain_colmap import run_plain_colmap
from benchmarks.metrics import evaluate
from benchmarks.run import run_child
from rigsfm.core.rig import load_rigs
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    # Seed 1: on seed 3 the paper's 8-point F locks onto the ground plane for one pair (13.8 deg off, BA RMS
    # 5.9 px), the weakness benchmarks/README.md measures; this test checks the baseline's mechanics.
    return render_dataset(root / "scene", SceneOptions(num_rigs=3, arc_deg=90.0, image_scale=0.5, seed=1))


def test_paper_baseline_registers_the_chain_metric_and_close_to_truth(scene):
    rec, report = run_paper(scene.root)
    assert report["stopped"] is None and report["metric"] is True
    assert all(pair["inliers"] > 200 and pair["ba_rms_px"] < 0.5 for pair in report["pairs"])
    accuracy = evaluate(rec, scene.load_ground_truth(), metric=True)
    narrow, wide = accuracy["narrow"], accuracy["wide"]
    assert narrow["registered"] == 3 and narrow["pairs"] == 3
    # Calibration noise (E^sl off by 0.05-0.1 deg, intrinsics) bounds what any method can reach.
    assert 0.01 < narrow["relative_rotation_deg"]["max"] < 0.4
    assert narrow["translation_direction_deg"]["max"] < 1.0
    # The scale is chained through shared points: the distance that scale.yaml does not fix is right too.
    assert wide["distance_error_percent"]["max"] < 0.5
    for rig in load_rigs(scene.rigs):  # narrow poses are E^sl (as calibrated) times the wide poses
        wide = rec.find_image_with_name(f"{rig.name}/wide/frame0000.png")
        narrow = rec.find_image_with_name(f"{rig.name}/narrow/frame0000.png")
        expected = rig.narrow_from_wide * wide.cam_from_world()
        np.testing.assert_allclose(narrow.cam_from_world().matrix(), expected.matrix(), atol=1e-9)


def test_plain_colmap_registers_no_narrow_camera_on_a_featureless_centre(scene, tmp_path):
    rec, report = run_plain_colmap(scene.images, tmp_path / "colmap")
    assert report["mean_keypoints"]["narrow"] < 10 and report["mean_keypoints"]["wide"] > 1000
    assert report["num_cameras_created"] == 6  # one guessed camera per image: no rig, no calibration
    accuracy = evaluate(rec, scene.load_ground_truth(), metric=False, align=True)
    assert accuracy["narrow"]["registered"] == 0 and accuracy["narrow"]["total"] == 3


def test_relative_scale_recovers_a_known_ratio():
    rng = np.random.default_rng(0)
    points_in_b = rng.uniform([-5, -3, 8], [5, 3, 20], size=(40, 3))  # metres, in the shared rig b
    b_from_a = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.3, 0.0])), np.array([4.0, 0.0, 1.0]))
    c_from_b = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.25, 0.0])), np.array([3.0, 0.0, 0.5]))
    s_ab, s_bc = np.linalg.norm(b_from_a.translation), np.linalg.norm(c_from_b.translation)

    def unit(t, s):
        return pycolmap.Rigid3d(t.rotation, t.translation / s)

    previous = PairResult("a", "b", second_from_first=unit(b_from_a, s_ab))
    current = PairResult("b", "c", second_from_first=unit(c_from_b, s_bc))
    for k, x_b in enumerate(points_in_b):
        previous.points[100 + k] = (b_from_a.inverse() * x_b) / s_ab
        previous.second_keypoint[100 + k] = k
        current.points[k] = x_b / s_bc
    ratio, shared = relative_scale(previous, current)
    assert shared == 40
    assert ratio == pytest.approx(s_bc / s_ab, rel=1e-9)
    current.points = {k + 1000: x for k, x in current.points.items()}  # nothing shared: the chain stops
    assert relative_scale(previous, current) == (None, 0)


def test_similarity_alignment_removes_gauge_and_scale(scene):
    truth = scene.load_ground_truth()
    moved = pycolmap.Reconstruction(truth)
    moved.transform(pycolmap.Sim3d(0.37, pycolmap.Rotation3d(np.array([0.2, -0.1, 0.4])), np.array([3.0, 1.0, -2.0])))
    assert evaluate(moved, truth, metric=True)["narrow"]["distance_error_percent"]["max"] == pytest.approx(63.0)
    aligned = evaluate(moved, truth, metric=False, align=True)["narrow"]
    assert aligned["distance_error_percent"]["max"] < 1e-6 and aligned["relative_rotation_deg"]["max"] < 1e-5


def test_worker_process_reports_time_memory_and_model(scene, tmp_path):
    report = run_child("paper", scene.root, tmp_path / "paper")
    assert report["ok"], report.get("error")
    assert 100 < report["peak_rss_mb"] < 4000 and 0 < report["time_s"] < report["process_s"]
    model = pycolmap.Reconstruction(tmp_path / "paper" / "model")
    assert model.num_reg_frames() == 3


@pytest.mark.slow
def test_trust_benchmark_prepares_and_measures_a_scene(tmp_path):
    """benchmarks/trust.py, whose tables back the README's coverage claim, end to end on one 2-rig scene: mapped,
    adjusted with the calibration fixed and refined, each band scored against the true floor correspondences,
    the oracle beside them. (Its prepare step once called the mapper with an argument that no longer existed.)"""
    from benchmarks.trust import Scene, measure, prepare

    scene = Scene("r2", "2 rigs 60°", SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.5, seed=1))
    prepare(scene, tmp_path)
    result = measure(scene, tmp_path)
    assert "error" not in result, result["error"]
    assert result["frames"] == 2
    oracle = result["variants"]["oracle"]["accuracy"]["relative_rotation_deg"]["max"]
    for variant in ("fixed", "refine"):
        (band,) = result["variants"][variant]["bands"]  # one pair; measured: 96 true floor points inside the band
        assert band["points"] == "floor" and band["num_true_points"] >= 50 and band["coverage"] >= 0.85, band
        assert band["predicted_coverage_mean"] == pytest.approx(0.95, abs=0.02)
    # measured: refined 0.216 deg against the oracle's 0.255 (2-rig scenes reach up to 1.31x at their worst pair)
    assert result["variants"]["refine"]["accuracy"]["relative_rotation_deg"]["max"] <= 1.5 * oracle


def test_mappers_benchmark_maps_adjusts_and_scores(three_rig_run, tmp_path, capsys):
    """benchmarks/mappers.py (the hierarchical-mapping table) on the session's 3-rig run: COLMAP's hierarchical
    mapper with rigsfm's incremental settings, then rigsfm's adjustment, scored against the truth."""
    from benchmarks.mappers import main

    dataset, out, _ = three_rig_run
    assert main([str(dataset.root), str(out), "--methods", "hierarchical-16x2", "--out", str(tmp_path)]) == 0
    assert "| hierarchical-16x2 |" in capsys.readouterr().out
    (report,) = (json.loads(p.read_text()) for p in tmp_path.glob("*/report.json"))
    assert "error" not in report, report["error"]
    assert report["num_wide"] == 3 and report["models"] == [3] and report["mapping_s"] > 0
    narrow = report["narrow"]
    assert narrow["registered"] == narrow["total"] == 3
    assert narrow["relative_rotation_deg"]["max"] < 0.3  # measured 0.196 deg, as the global and incremental mappers


def test_three_rig_bands_table_pools_true_points_and_leaves_out_partial_networks():
    """benchmarks/three_rig_bands.py's table (the rendered 3-rig row of benchmarks/README): coverage pooled over the
    true correspondences (a pair's weight is its number of true points), networks without 3 frames left out."""
    from benchmarks.three_rig_bands import table

    def pairs(*rows):
        return [{"num_true_points": n, "coverage": c, "band_px": b, "predicted_below_85": p} for n, c, b, p in rows]

    results = [{"seed": 0, "frames": 3,
                "sampled": {"seconds": 4.0, "pairs": pairs((300, 1.0, 10, 0.1), (100, 0.6, 12, 0.2))},
                "linear": {"seconds": 0.02, "pairs": pairs((300, 0.9, 9, 0.0), (100, 0.5, 11, 0.1))}},
               {"seed": 1, "frames": 2, "sampled": {"seconds": 9.0, "pairs": pairs((999, 0.0, 99, 1.0))},
                "linear": {"seconds": 9.0, "pairs": pairs((999, 0.0, 99, 1.0))}},
               {"seed": 2, "error": "mapping failed"}]
    rows = table(results).splitlines()
    assert rows[2] == "| sampled | 1 | 2 | 0.900 | 50.0 % / 15.0 % | 11.00 | 4.00 |"  # (300 + 60) / 400
    assert rows[3] == "| linear | 1 | 2 | 0.800 | 50.0 % / 5.0 % | 10.00 | 0.02 |"  # (270 + 50) / 400


def test_networks_records_the_network_test_and_the_contradicted_warning():
    from dataclasses import asdict

    from benchmarks.networks import decisions_record, decisions_table
    from rigsfm.run.adjustment.decisions import contradiction
    from rigsfm.run.adjustment.result import CalibrationDecision

    def summary(network_chi2: float, held: bool) -> dict:
        decisions = [CalibrationDecision(f"rig0{i}", held, "", 0.9, 5.0 + i, 4, 9.49, network_chi2, 15)
                     for i in range(1, 5)]
        warning = contradiction(decisions)  # as the run writes it into summary.json's warnings
        return {"calibration_decisions": [asdict(d) for d in decisions],
                "warnings": ["NOT METRIC: ..."] + ([warning] if warning else [])}

    wrong, benign, refined = (decisions_record(summary(c, h)) for c, h in ((80.2, True), (28.4, True), (12.0, False)))
    assert wrong["contradicted"] and not benign["contradicted"] and not refined["contradicted"]
    assert wrong["network_dof"] == 15 and wrong["network_chi2"] == 80.2
    assert round(wrong["limit_hold"], 1) == 25.0 and round(wrong["limit_contradicted"], 1) == 37.7
    assert wrong["refined"] == [] and refined["refined"] == ["rig01", "rig02", "rig03", "rig04"]
    rows = decisions_table([{"network": n, "default": {"decisions": d}}
                            for n, d in (("a", wrong), ("b", benign), ("c", refined))]).splitlines()
    assert rows[2] == "| a | 4 | 15 | 80.2 | 25.0 | 37.7 | held | yes |"
    assert rows[3].endswith("| held | no |") and rows[4].endswith("| refined | no |")
