"""Never worse than holding the calibration: the adjustment refines a rig's intrinsics and E^sl only where the images
inform them (``rigsfm.run.adjustment.decisions.hold_or_refine``), on a rendered weak network registered from simulated clicks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rigsfm.core.workspace import Workspace, colmap_log_to
from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.inputs.database import create_database
from rigsfm.run.mapping.mapper import run_mapping
from rigsfm.run.matching.extract import extract_features
from rigsfm.run.matching.manual_matches import (
    read_manual_matches,
    validate_manual_matches,
    write_manual_matches,
)
from rigsfm.run.matching.manual_merge import add_manual_matches
from rigsfm.run.options import AdjustOptions, Calibration, MappingOptions, MatchingOptions
from rigsfm.run.pipeline import load_inputs
from rigsfm.synth.clicks import simulate_clicks
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions, build_arena
from rigsfm.synth.truth import compare_to_ground_truth

pytestmark = pytest.mark.slow  # renders and maps a scene

A, B = "rig01/wide/frame0000.png", "rig02/wide/frame0000.png"


def _clicks_only(root: Path, options: SceneOptions, seed: int):
    """The scene mapped from 34 simulated clicks alone (1 px noise, 7 of them wrong; no SIFT matches), as a user
    registers two rigs too far apart for features: ``(inputs, mapping model, ground truth)``."""
    dataset = render_dataset(root / "scene", options)
    truth = dataset.load_ground_truth()
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)
    csv = write_manual_matches(root / "clicks.csv",
                               simulate_clicks(build_arena(options), truth, A, B, n=34, seed=seed).rows)
    workspace = Workspace(root / "run")
    workspace.root.mkdir(parents=True)
    with colmap_log_to(workspace.colmap_log):
        create_database(workspace.database, inputs.rigs, inputs.images)
        extract_features(workspace.database, inputs.image_dir, inputs.images, MatchingOptions())
        add_manual_matches(workspace.database, validate_manual_matches(csv, read_manual_matches(csv), inputs.images,
                                                                       inputs.rigs))
        mapped = run_mapping(workspace, inputs.image_dir, MappingOptions(few_matches=True), num_wide=2).reconstruction
    return inputs, mapped, truth


def test_a_weak_network_is_never_worse_than_holding_the_calibration(tmp_path):
    """Two rigs 150 deg apart (wide f = 500 px), registered from 34 clicks: the images inform no direction of the
    calibration more than rigs.yaml's sigmas do, so the default adjustment holds it, and its narrow rotation error is
    that of --fixed-calibration. Refining every rig's calibration (the default before) gave 1.28x the rotation error
    and 1.9x the true epipolar distance's 95th percentile on this scene (benchmarks/hold_or_refine.py)."""
    inputs, mapped, truth = _clicks_only(tmp_path, SceneOptions(num_rigs=2, arc_deg=150, seed=0, wide_focal=500.0),
                                         seed=0)
    errors = {}
    for variant, options in (("fixed", AdjustOptions(calibration=Calibration.FIXED)), ("default", AdjustOptions())):
        result = adjust(mapped, inputs.rigs, inputs.scale, options, inputs.priors)
        errors[variant] = compare_to_ground_truth(result.reconstruction, truth, "narrow")["relative_rotation_deg"]["max"]
    print(f"\nnarrow rotation error: {errors}")
    # Holding every rig is --fixed-calibration's adjustment: the same numbers, up to Ceres' last digits.
    assert errors["default"] <= errors["fixed"] * (1 + 1e-6), errors
    np.testing.assert_allclose(errors["default"], errors["fixed"], rtol=1e-6)
    assert [d.held for d in result.decisions] == [True, True]
    assert all("inform no direction" in d.reason for d in result.decisions)


def test_images_that_contradict_rigs_yaml_far_beyond_its_sigmas_are_said():
    """Every rig is held where the network's consistency test fails (95 %), and built on rigs.yaml's values; far
    beyond (99.9 %: a focal length 1 % off on one rig of four gave chi-square 80.2 on 15 dof, this rig's 37.3 against
    7.8) those values are what the images contradict, so the run says so, naming the rig that disagrees most."""
    from rigsfm.run.adjustment.decisions import contradiction
    from rigsfm.run.adjustment.result import CalibrationDecision

    def decisions(network: float) -> list[CalibrationDecision]:
        return [CalibrationDecision(rig, True, "held", 0.9, chi2, dof, limit, network, 15)
                for rig, chi2, dof, limit in (("rig01", 37.3, 3, 7.81), ("rig02", 16.1, 4, 9.49),
                                              ("rig03", 14.0, 4, 9.49), ("rig04", 8.9, 4, 9.49))]

    warning = contradiction(decisions(80.2))
    assert warning is not None and warning.startswith("CALIBRATION CONTRADICTED: ") and "(chi-square 80.2 > 37.7" in warning
    assert "most rig01: 37.3 against 7.8" in warning and "check rig01's entry in rigs.yaml" in warning
    assert contradiction(decisions(30.0)) is None  # held (above 25.0, the 95 % quantile), not contradicted
    assert contradiction([CalibrationDecision("rig01", True, "no image observes its calibration")]) is None
