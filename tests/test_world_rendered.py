"""The analyst's world on rendered scenes with exact ground truth (the bands measured in benchmarks/README.md).

Arena: 8 rigs round a featureless centre (812x617), whose sparse model holds almost no floor, so the floor comes
from floor matching. With the exact calibration (rigs_exact.yaml) the floor frame meets the issue's bands:
camera heights within 3 cm, the floor normal within 0.1 deg, distances between floor points mapped through
``ground_from_image`` within 1 % (measured: 15 mm, 0.01-0.02 deg, 0.3 %). With the realistic rigs.yaml the
calibration errors set the limit (camera positions alone are off by up to 26 mm in height after a similarity
alignment), so that run is held to the oracle: the same world stage on the fixed-calibration oracle model.

Crowd: 6 rigs round a textured centre, narrow images of every rig share the frame name frame0000.png. The
self-check's measured epipolar distances agree with those of the true correspondences of the same points within
20 % (pooled; per pair on top of the keypoints' noise), and it fails only pairs whose true correspondences do lie
outside the band. (frames_per_rig stays 1: with two frames per rig the current epipolar band is inflated by the
scale gauge of the pose covariance, which fixes a coordinate of the 0.6 mm baseline between a rig's two frames.)
"""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
from world_truth import floor_errors, ground_distance_errors, self_check_truth

from rigsfm.run.checks.self_check import epipolar_self_check
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import NarrowMode, RunOptions, SelfCheckOptions, WorldOptions
from rigsfm.run.pipeline import load_inputs, run
from rigsfm.run.world.frame import ground_maps, place_in_world
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions
from rigsfm.synth.truth import oracle

pytestmark = pytest.mark.slow

HEADS = RunOptions(world=WorldOptions(plane_heights=(1.7,)))


def world_numbers(narrow: dict, rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    return {**floor_errors(rec, truth),
            **{f"distance_pct_{h}": ground_distance_errors(narrow, rec, truth, h) for h in (0.0, 1.7)}}


@pytest.fixture(scope="module")
def arena(tmp_path_factory, rendered):
    root = tmp_path_factory.mktemp("arena")
    dataset = rendered(SceneOptions(num_rigs=8, image_scale=0.5, seed=0))
    truth = dataset.load_ground_truth()
    results = {}
    for label, rigs in (("exact", dataset.rigs_exact), ("realistic", dataset.rigs)):
        out = root / label
        result = run(dataset.images, rigs, out, dataset.scale, HEADS)
        narrow = json.loads((out / "narrow_poses.json").read_text())
        results[label] = {"summary": result.summary, "narrow": narrow,
                          "numbers": world_numbers(narrow, result.reconstruction, truth)}
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)  # the oracle of the realistic run
    limit = oracle(pycolmap.Reconstruction(root / "realistic" / "sparse"), truth, inputs.rigs, inputs.scale)
    world = place_in_world(limit, dataset.images, inputs.scale, [r.name for r in inputs.rigs], HEADS.world)
    narrow = narrow_poses(limit, metric=True, world=world.to_dict(),
                          ground=ground_maps(limit, world.plane_heights))
    results["oracle"] = {"numbers": world_numbers(narrow, limit, truth)}
    return results


def test_floor_is_found_by_floor_matching(arena):
    for label in ("exact", "realistic"):
        world = arena[label]["summary"].world
        floor = world.floor
        assert world.frame == "floor"
        assert floor["matching"]["ran"] and floor["points_by_source"]["matched"] > 200  # ~0 sparse floor points
        assert max(abs(r) for r in floor["marker_residuals"]) < 0.02  # the bar lies on the floor
        assert not any(w.startswith(("NO FLOOR", "FLOOR")) for w in arena[label]["summary"].warnings)


def test_exact_calibration_meets_the_issue_bands(arena):
    numbers = arena["exact"]["numbers"]
    assert numbers["height_error_mm"]["max"] < 30.0
    assert numbers["normal_deg"]["per_camera_median"] < 0.1 and numbers["normal_deg"]["aligned"] < 0.1
    assert numbers["distance_pct_0.0"]["max"] < 1.0
    assert numbers["distance_pct_1.7"]["max"] < 1.0


def test_realistic_calibration_is_as_good_as_the_oracle(arena):
    run_, limit = arena["realistic"]["numbers"], arena["oracle"]["numbers"]
    # The run refines the calibration, the oracle holds it: its heights may be a little worse (benchmarks/README.md)
    assert run_["height_error_mm"]["max"] <= 1.25 * limit["height_error_mm"]["max"] + 2.0
    assert run_["normal_deg"]["aligned"] <= 1.1 * limit["normal_deg"]["aligned"] + 0.01
    for plane in ("distance_pct_0.0", "distance_pct_1.7"):
        assert run_[plane]["max"] <= 1.25 * limit[plane]["max"] + 0.05  # 2.17 vs 1.88 % measured
    assert run_["height_error_mm"]["max"] < 50.0 and run_["distance_pct_0.0"]["max"] < 2.5  # absolute sanity


def test_narrow_poses_hold_the_frame_and_ground_maps(arena):
    narrow = arena["exact"]["narrow"]
    assert narrow["world"]["frame"] == "floor" and narrow["ground"]["plane_heights_m"] == [0.0, 1.7]
    assert all(len(entry["ground"]) == 2 for entry in narrow["narrow"])
    gsd = [entry["ground"][0]["gsd_mm_per_px"] for entry in narrow["narrow"]]
    assert all(7.0 < g < 10.0 for g in gsd)  # ~9 mm per pixel on the floor at 812x617
    assert narrow["ground"]["seen_by_two_or_more_m2"][0] > 50.0


@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    root = tmp_path_factory.mktemp("crowd")
    dataset = render_dataset(root / "scene", SceneOptions(num_rigs=6, image_scale=0.5, seed=0, textured_centre=True))
    truth = dataset.load_ground_truth()
    results = {}
    for label, rigs in (("exact", dataset.rigs_exact), ("realistic", dataset.rigs)):
        out = root / label
        # Without narrow observations: they bring the epipolar error below the keypoints' own noise, where the
        # check has nothing to measure (tests/test_narrow_obs.py checks them).
        result = run(dataset.images, rigs, out, dataset.scale, RunOptions(narrow=NarrowMode.OFF))
        check = result.self_check  # the run's own, every pair with its distances
        measured = [p for p in check.pairs if p.verdict in ("ok", "failed")]
        true = [self_check_truth(p, result.reconstruction, truth) for p in measured]
        results[label] = {"summary": result.summary, "pairs": measured, "true": true, "all": check.pairs,
                          "reconstruction": result.reconstruction, "out": out}
    results["dataset"] = dataset
    return results


def test_self_check_is_in_the_summary(crowd):
    summary = crowd["realistic"]["summary"]
    check = summary.epipolar_self_check
    assert check.frames == ["frame0000.png"] and len(check.pairs) == len(crowd["realistic"]["all"])
    failed = [p for p in check.pairs if p.verdict == "failed"]
    assert any(w.startswith("EPIPOLAR CHECK FAILED") for w in summary.warnings) == bool(failed)


@pytest.mark.parametrize("label", ["realistic", "exact"])
def test_self_check_measures_the_true_distances_within_20_percent(crowd, label):
    pairs, true = crowd[label]["pairs"], crowd[label]["true"]
    assert len(pairs) >= 10 and all(p.matches >= 50 for p in pairs)
    measured, truth = np.concatenate([p.distances_px for p in pairs]), np.concatenate(true)
    assert np.median(measured) == pytest.approx(np.median(truth), rel=0.2)
    assert np.percentile(measured, 95) == pytest.approx(np.percentile(truth, 95), rel=0.2)
    for pair, t in zip(pairs, true):  # per pair, on top of the keypoints' own noise (the check allows 1 px)
        if np.median(t) >= 1.0:
            assert pair.median_px == pytest.approx(np.median(t), rel=0.2)
        assert pair.p95_px == pytest.approx(np.percentile(t, 95), rel=0.2, abs=1.0)


def test_self_check_on_reduced_images_measures_the_true_distances(crowd):
    """SIFT on the narrow images halved (as on full-size 1624x1234 images, SelfCheckOptions.sift_size): fewer
    matches (a median 158 instead of 339 here), the same distances."""
    dataset, realistic = crowd["dataset"], crowd["realistic"]
    rec = realistic["reconstruction"]
    narrow_poses = json.loads((realistic["out"] / "narrow_poses.json").read_text())
    check = epipolar_self_check(rec, dataset.images, narrow_poses, SelfCheckOptions(sift_size=406))  # 812x617 / 2
    pairs = [p for p in check.pairs if p.verdict in ("ok", "failed")]
    assert len(pairs) >= 10  # with a verdict: each has at least MIN_MATCHES matches
    assert np.median([p.matches for p in pairs]) < 0.7 * np.median([p.matches for p in realistic["pairs"]])
    true = [self_check_truth(p, rec, dataset.load_ground_truth()) for p in pairs]
    measured, truth = np.concatenate([p.distances_px for p in pairs]), np.concatenate(true)
    assert np.median(measured) == pytest.approx(np.median(truth), rel=0.1)
    assert np.percentile(measured, 95) == pytest.approx(np.percentile(truth, 95), rel=0.1)


@pytest.mark.parametrize("label", ["realistic", "exact"])
def test_self_check_fails_only_pairs_whose_truth_exceeds_the_band(crowd, label):
    """No false alarm: a failed pair's true correspondences exceed the band. A pair whose true 95th percentile
    exceeds the band by more than the 1 px noise allowance (+20 %) fails. (Even the exact calibration has pairs
    whose true distances exceed the current band, which leaves out part of the registration error.)"""
    for pair, t in zip(crowd[label]["pairs"], crowd[label]["true"]):
        true_p95 = np.percentile(t, 95)
        if pair.verdict == "failed":
            assert true_p95 > pair.band_px, pair
        if true_p95 > 1.2 * (pair.band_px + 1.0):
            assert pair.verdict == "failed", pair
