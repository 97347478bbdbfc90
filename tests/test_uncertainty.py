"""The 95 % epipolar band is calibrated: on synthetic networks with exact ground truth (mapping + rig
constraints as in `rigsfm run`, exact calibration, 0.5 px keypoint noise), true correspondences of narrow
pairs fall inside the band at about the stated rate."""

import itertools
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rigsfm.run.deliver import narrow_images
from rigsfm.core.workspace import Workspace
from rigsfm.run.mapping import run_mapping
from rigsfm.run.options import MappingOptions
from rigsfm.run.adjust import adjust
from rigsfm.run.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.uncertainty import (correspondence_check, narrow_epipolar_bands, rig_pose_covariance,
                                sample_narrow_from_world)
from synthetic_db import make_network

NOISE_PX = 0.5


def estimate(root: Path, seed: int, num_rigs: int = 4, noise_px: float = NOISE_PX):
    root.mkdir(parents=True)
    net = make_network(root, num_rigs=num_rigs, seed=seed, noise_px=noise_px)
    mapped = run_mapping(Workspace(root), root, MappingOptions(), num_wide=num_rigs).reconstruction
    a, b = "rig01/wide/frame0000.png", f"rig{num_rigs:02d}/wide/frame0000.png"
    truth = net.ground_truth
    metres = float(np.linalg.norm(truth.find_image_with_name(a).projection_center()
                                  - truth.find_image_with_name(b).projection_center()))
    spec = ScaleSpec(root / "scale.yaml", (CameraDistance(a, b, metres),), ())
    return adjust(mapped, net.rigs, spec).reconstruction, truth


def sample_points(truth: pycolmap.Reconstruction, name: str, rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """World points on random rays of a true narrow camera at depths spanning the scene's points."""
    image = truth.find_image_with_name(name)
    camera = truth.cameras[image.camera_id]
    depth = np.asarray(image.cam_from_world() * np.array([p.xyz for p in truth.points3D.values()]))[:, 2]
    low, high = np.percentile(depth[depth > 0], [5, 95])
    pixels = rng.uniform([0, 0], [camera.width, camera.height], (n, 2))
    rays = np.column_stack([np.asarray(camera.cam_from_img(pixels)), np.ones(n)]) * rng.uniform(low, high, (n, 1))
    return np.asarray(image.cam_from_world().inverse() * rays)


def test_band_coverage_is_calibrated(tmp_path):
    point_inside, pair_inside, count = [], [], 0
    for seed in range(6):
        rec, truth = estimate(tmp_path / str(seed), seed)
        names = [im.name for im in narrow_images(rec)]
        pairs = list(itertools.combinations(names, 2))
        rng = np.random.default_rng(seed)
        covariance = rig_pose_covariance(rec)
        # The pixel noise is estimated from the residuals: it recovers the keypoint noise.
        assert covariance.sigma_px == pytest.approx(NOISE_PX, rel=0.2)
        assert np.all(covariance.block(covariance.fixed_frame_id) == 0)
        samples = sample_narrow_from_world(rec, covariance, names, 400, rng)
        bands = narrow_epipolar_bands(rec, pairs, seed=seed)
        for pair in pairs:
            distances, quantiles = correspondence_check(rec, truth, *pair, sample_points(truth, pair[0], rng), samples)
            if len(distances) < 10 or pair not in bands:
                continue
            count += 1
            point_inside.append(np.mean(distances <= quantiles))  # band at each point's own pixel and depth
            pair_inside.append(np.mean(distances <= bands[pair]["band_px"]))  # the one number per pair
    assert count >= 20
    coverage, pair_coverage = float(np.mean(point_inside)), float(np.mean(pair_inside))
    print(f"95 % band coverage over {count} pairs: per point {coverage:.3f}, pair band {pair_coverage:.3f}")
    assert 0.85 <= coverage <= 1.0
    assert coverage <= pair_coverage <= 1.0  # the pair's band is the largest over its points and depths


def test_band_grows_with_pixel_noise(tmp_path):
    """Four times the keypoint noise: about four times the band (the covariance scales with sigma^2)."""
    bands = []
    for noise, sub in ((0.25, "low"), (1.0, "high")):
        rec, _ = estimate(tmp_path / sub, seed=3, num_rigs=3, noise_px=noise)
        names = [im.name for im in narrow_images(rec)]
        bands.append(np.array([b["band_px"] for b in narrow_epipolar_bands(rec, list(itertools.combinations(names, 2))).values()]))
    ratio = bands[1] / bands[0]
    assert len(ratio) == 3 and np.all((ratio > 2.5) & (ratio < 6.0)), ratio
