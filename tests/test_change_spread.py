"""The hold-or-refine test's null: the refined calibration's change from rigs.yaml spreads as the adjustment computes
it, which weighs a static rig's repeated views of a point as independent while the covariance counts them as
correlated (``JointCovariance.change_excess``; benchmarks/README.md, "Why the refined calibration moves further than
its posterior")."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from synthetic_db import make_network, perturbed_model
from test_static_frames import _second_static_frame

from rigsfm.run.adjustment.adjust import _refine
from rigsfm.run.adjustment.covariance import joint_covariance
from rigsfm.run.adjustment.decisions import hold_or_refine
from rigsfm.run.adjustment.priors import calibration_priors
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.options import AdjustOptions

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks.change_spread import gaussian_rigs  # the benchmark's draw of rigs.yaml

RIGS = ("rig01", "rig02", "rig03", "rig04")


def _scale(truth, folder: Path) -> ScaleSpec:
    """scale.yaml's true distance between rig01's and rig03's wide cameras (a metric gauge)."""
    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    metres = float(np.linalg.norm(truth.find_image_with_name(a).projection_center()
                                  - truth.find_image_with_name(b).projection_center()))
    return ScaleSpec(Path(folder / "scale.yaml"), (CameraDistance(a, b, metres),), ())


def test_the_change_spreads_as_the_test_says_with_repeated_views(tmp_path):
    """4 rigs of two static frames each, the second frame's keypoints the first's (a static background's keypoint
    errors repeat), the noise model without inflation (the covariance's is then the draws' own), rigs.yaml drawn
    from its sigmas: over 30 draws the network's chi-square averages 0.79 of its dof (1 were the null exact). Against
    the posterior alone (the spread of a solve that weighs repeated views as the covariance does) it averaged 1.27:
    the solve counts each repeated view in full and moves the calibration further."""
    net = make_network(tmp_path, num_rigs=4, seed=3, num_points=300)
    truth = net.ground_truth
    spec = _scale(truth, tmp_path)
    priors = calibration_priors(net.rigs)
    options = replace(AdjustOptions(), pixel_sigma_inflation=1.0)
    rng = np.random.default_rng(0)
    ratios, before = [], []
    for draw in range(30):
        mapped = perturbed_model(truth, seed=100 + draw)
        for rig in RIGS:
            _second_static_frame(mapped, rig, np.zeros(3))
        rigs = gaussian_rigs(net.rigs, priors, rng, narrow_from_wide=False)
        result = _refine(mapped, rigs, spec, options, priors, frozenset())
        covariance = joint_covariance(result)
        assert covariance is not None and covariance.change_excess is not None
        network = next(d for d in hold_or_refine(result, covariance) if d.network_dof)
        ratios.append(network.network_chi2 / network.network_dof)
        network = next(d for d in hold_or_refine(result, replace(covariance, change_excess=None)) if d.network_dof)
        before.append(network.network_chi2 / network.network_dof)
    assert np.mean(ratios) < 1.05, (np.mean(ratios), np.mean(before))
    assert np.mean(before) > 1.15  # the draws do show the gap the excess closes


def test_without_repeated_views_the_test_is_the_posteriors(tmp_path):
    """One frame per rig (no residual the covariance weighs otherwise than the solve): no excess, and the decisions
    are those of ``prior - posterior`` to the last digit."""
    net = make_network(tmp_path, num_rigs=4, seed=3, num_points=300)
    truth = net.ground_truth
    spec = _scale(truth, tmp_path)
    priors = calibration_priors(net.rigs)
    rigs = gaussian_rigs(net.rigs, priors, np.random.default_rng(1), narrow_from_wide=False)
    result = _refine(perturbed_model(truth, seed=5), rigs, spec, AdjustOptions(), priors, frozenset())
    covariance = joint_covariance(result)
    assert covariance is not None and covariance.change_excess is None
