"""Mapping + rig constraints on a synthesized database with exact ground truth (no images needed)."""

import logging

import numpy as np
import pycolmap
import pytest
from synthetic_db import make_network

from rigsfm.core.workspace import Workspace
from rigsfm.run.adjustment.adjust import ScaleSource, adjust
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.mapping.mapper import run_mapping
from rigsfm.run.options import AdjustOptions, Calibration, Mapper, MappingOptions
from rigsfm.synth.truth import compare_to_ground_truth, oracle


def _gt_distance(gt, a, b):
    return float(np.linalg.norm(gt.find_image_with_name(a).projection_center()
                                - gt.find_image_with_name(b).projection_center()))


@pytest.mark.parametrize("num_rigs,mapper", [(2, "incremental"), (2, "global"), (5, "incremental"), (5, "global")])
def test_rig_network_matches_ground_truth_and_oracle(tmp_path, num_rigs, mapper):
    net = make_network(tmp_path, num_rigs=num_rigs, seed=num_rigs)
    mapped = run_mapping(Workspace(tmp_path), tmp_path, MappingOptions(mapper=Mapper(mapper)), num_wide=num_rigs).reconstruction
    assert mapped.num_reg_frames() == num_rigs

    a, b = "rig01/wide/frame0000.png", f"rig{num_rigs:02d}/wide/frame0000.png"
    spec = ScaleSpec(tmp_path / "scale.yaml", (CameraDistance(a, b, _gt_distance(net.ground_truth, a, b)),), ())
    result = adjust(mapped, net.rigs, spec, AdjustOptions(calibration=Calibration.FIXED))
    rec = result.reconstruction
    assert result.scale_source == ScaleSource.MEASUREMENTS
    assert abs(result.scale.residuals()[0]["residual_percent"]) < 1e-6

    # --fixed-calibration holds it exactly: intrinsics and E^sl unchanged to 1e-9.
    for rig in net.rigs:
        for sensor in ("wide", "narrow"):
            image = rec.find_image_with_name(f"{rig.name}/{sensor}/frame0000.png")
            np.testing.assert_allclose(rec.cameras[image.camera_id].params, rig.camera(sensor).params, atol=1e-9)
        narrow = rec.find_image_with_name(f"{rig.name}/narrow/frame0000.png")
        sensor_from_rig = rec.rig(rec.frame(narrow.frame_id).rig_id).sensor_from_rig(
            rec.cameras[narrow.camera_id].sensor_id)
        np.testing.assert_allclose(sensor_from_rig.matrix(), rig.narrow_from_wide.matrix(), atol=1e-9)
        wide = rec.find_image_with_name(f"{rig.name}/wide/frame0000.png")
        composed = rig.narrow_from_wide * wide.cam_from_world()
        np.testing.assert_allclose(narrow.cam_from_world().matrix(), composed.matrix(), atol=1e-9)

    metrics = compare_to_ground_truth(rec, net.ground_truth)
    limit = compare_to_ground_truth(oracle(rec, net.ground_truth, net.rigs, spec), net.ground_truth)
    assert metrics["registered"] == num_rigs
    # Within 10 % of the accuracy limit (plus a floor for numerically tiny limits).
    assert metrics["relative_rotation_deg"]["max"] <= 1.1 * limit["relative_rotation_deg"]["max"] + 1e-3
    assert metrics["relative_rotation_deg"]["max"] < 0.5
    # Narrow centres are metric: pairwise distances within 0.5 % of the truth (the scale trap would
    # leave the 5 cm narrow offsets scaled by the arbitrary mapping units).
    assert metrics["distance_error_percent"]["max"] < 0.5

    # The default refines the (here exact) calibration with a good board's priors: no worse than the oracle that
    # holds it exactly, beyond the image noise (a few thousandths of a degree).
    refined = adjust(mapped, net.rigs, spec)
    metrics = compare_to_ground_truth(refined.reconstruction, net.ground_truth)
    assert metrics["relative_rotation_deg"]["max"] <= 1.5 * limit["relative_rotation_deg"]["max"] + 2e-3
    assert metrics["distance_error_percent"]["max"] < 0.5
    assert abs(refined.scale.residuals()[0]["residual_percent"]) < 0.1  # inside the adjustment, weighed at 1 cm


def test_scale_trap_is_avoided(tmp_path):
    """The mapped world is in arbitrary units; E^sl must come out metric, not scaled with the world."""
    net = make_network(tmp_path, num_rigs=3, seed=7)
    mapped = run_mapping(Workspace(tmp_path), tmp_path, MappingOptions(), num_wide=3).reconstruction
    a, b = "rig01/wide/frame0000.png", "rig02/wide/frame0000.png"
    true_distance = _gt_distance(net.ground_truth, a, b)
    mapped_distance = float(np.linalg.norm(mapped.find_image_with_name(a).projection_center()
                                           - mapped.find_image_with_name(b).projection_center()))
    assert abs(mapped_distance / true_distance - 1.0) > 0.05, "mapping units happen to be metric; test is void"
    result = adjust(
        mapped, net.rigs, ScaleSpec(tmp_path / "s.yaml", (CameraDistance(a, b, true_distance),), ()))
    for rig in net.rigs:
        wide = result.reconstruction.find_image_with_name(f"{rig.name}/wide/frame0000.png")
        narrow = result.reconstruction.find_image_with_name(f"{rig.name}/narrow/frame0000.png")
        baseline = np.linalg.norm(wide.projection_center() - narrow.projection_center())
        assert baseline == pytest.approx(np.linalg.norm(rig.narrow_from_wide.translation), abs=1e-9)


def test_without_scale_the_result_is_flagged_non_metric(tmp_path, caplog):
    """Flagged once: not again by each of the sampled band's calibration draws (a 3-rig run without scale.yaml
    printed the warning 41 times)."""
    from rigsfm.run.adjustment.sampled import sampled_pair_bands

    net = make_network(tmp_path, num_rigs=3, seed=3)
    mapped = run_mapping(Workspace(tmp_path), tmp_path, MappingOptions(), num_wide=3).reconstruction
    with caplog.at_level(logging.WARNING):
        result = adjust(mapped, net.rigs, None)
        sampled_pair_bands(result, None, num_draws=3)
    assert result.scale_source == ScaleSource.NONE
    assert result.scale is None and result.metres_per_mapping_unit is None  # summary.json's scale claimed metres
    assert isinstance(result.reconstruction, pycolmap.Reconstruction)
    assert [r.getMessage() for r in caplog.records if "NOT metric" in r.getMessage()] == [
        "No scale file and no narrow observations: the result is NOT metric"]


def test_scale_from_narrow_baselines_with_honest_uncertainty(tmp_path):
    """Textured narrow views: the metric E^sl baselines alone set the scale, and its reported
    uncertainty covers the actual error."""
    net = make_network(tmp_path, num_rigs=4, seed=11, narrow_observations=True, noise_px=0.5)
    mapped = run_mapping(Workspace(tmp_path), tmp_path, MappingOptions(), num_wide=4).reconstruction
    result = adjust(mapped, net.rigs, None)
    assert result.scale_source == ScaleSource.NARROW_BASELINES
    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    estimated = _gt_distance(result.reconstruction, a, b)
    relative_error = abs(estimated / _gt_distance(net.ground_truth, a, b) - 1.0)
    sigma = result.scale_relative_sigma
    assert 0 < sigma < 0.05
    assert relative_error < 4 * sigma, (relative_error, sigma)
