"""The image-noise part of the joint covariance: on synthetic networks with exact ground truth (mapping + adjustment as
in `rigsfm run`, 0.5 px keypoint noise) and a calibration known almost exactly (priors 1000x tighter than a good
board's), the 95 % band holds the true correspondences at about the stated rate and grows with the pixel noise.
The calibration's own part is tested in test_trust.py."""

import itertools
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from synthetic_db import make_network

from rigsfm.core.geometry import correspondence_check
from rigsfm.core.workspace import Workspace
from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.adjustment.priors import BoardDefaults, calibration_priors
from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
from rigsfm.run.deliver import narrow_images
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.mapping.mapper import run_mapping
from rigsfm.run.options import AdjustOptions, MappingOptions
from rigsfm.run.world.analysis_floor import find_floor

NOISE_PX = 0.5
TIGHT = BoardDefaults(focal_relative=1.2e-6, principal_point_px=6e-4, radial=(5e-7, 3e-7, 1e-7), tangential=1e-8,
                      rotation_deg=4.5e-5, translation_m=6e-7)


def estimate(root: Path, seed: int, num_rigs: int = 4, noise_px: float = NOISE_PX):
    root.mkdir(parents=True)
    net = make_network(root, num_rigs=num_rigs, seed=seed, noise_px=noise_px)
    mapped = run_mapping(Workspace(root), root, MappingOptions(), num_wide=num_rigs).reconstruction
    a, b = "rig01/wide/frame0000.png", f"rig{num_rigs:02d}/wide/frame0000.png"
    truth = net.ground_truth
    metres = float(np.linalg.norm(truth.find_image_with_name(a).projection_center()
                                  - truth.find_image_with_name(b).projection_center()))
    spec = ScaleSpec(root / "scale.yaml", (CameraDistance(a, b, metres),), ())
    result = adjust(mapped, net.rigs, spec, AdjustOptions(pixel_sigma_inflation=1.0),
                    calibration_priors(net.rigs, defaults=TIGHT))
    return result, truth


def sample_points(truth: pycolmap.Reconstruction, name_i: str, name_j: str, rng: np.random.Generator,
                  n: int = 3000) -> np.ndarray:
    """World points on random pixels of true narrow camera i at depths uniform in inverse depth from 0.1x to 100x
    the pair's distance (the band's analysis points when there is no floor)."""
    image_i, image_j = truth.find_image_with_name(name_i), truth.find_image_with_name(name_j)
    camera = truth.cameras[image_i.camera_id]
    distance = float(np.linalg.norm(image_i.projection_center() - image_j.projection_center()))
    pixels = rng.uniform([0, 0], [camera.width, camera.height], (n, 2))
    depth = 1.0 / rng.uniform(1.0 / (100 * distance), 1.0 / (0.1 * distance), n)
    rays = np.column_stack([np.asarray(camera.cam_from_img(pixels)), np.ones(n)]) * depth[:, None]
    return np.asarray(image_i.cam_from_world().inverse() * rays)


def test_band_coverage_of_the_image_noise(tmp_path):
    inside, count = [], 0
    for seed in range(6):
        result, truth = estimate(tmp_path / str(seed), seed)
        # The pixel noise is estimated from the residuals: it recovers the keypoint noise.
        assert result.pixel_sigma == pytest.approx(NOISE_PX, rel=0.2)
        plane, source = find_floor(result.reconstruction, result.scale_spec)
        uncertainty = estimate_uncertainty(result, floor=plane, floor_source=source)
        assert uncertainty.floor == "none"  # random points: no floor, points at every depth
        rng = np.random.default_rng(seed)
        for (name_i, name_j), band in uncertainty.bands.items():
            assert band.points == "depths"
            distances = correspondence_check(result.reconstruction, truth, name_i, name_j,
                                             sample_points(truth, name_i, name_j, rng))
            if len(distances) < 10:
                continue
            count += 1
            inside.append(np.mean(distances <= band.band_px))
    assert count >= 20
    coverage = float(np.mean(inside))
    print(f"95 % band coverage over {count} pairs: {coverage:.3f}")
    assert 0.88 <= coverage <= 1.0


def test_band_grows_with_pixel_noise(tmp_path):
    """Four times the keypoint noise: about four times the band (the covariance scales with sigma^2)."""
    bands = []
    for noise, sub in ((0.25, "low"), (1.0, "high")):
        result, _ = estimate(tmp_path / sub, seed=3, num_rigs=3, noise_px=noise)
        names = [im.name for im in narrow_images(result.reconstruction)]
        plane, source = find_floor(result.reconstruction, result.scale_spec)
        found = estimate_uncertainty(result, floor=plane, floor_source=source).bands
        bands.append(np.array([found[pair].band_px for pair in itertools.combinations(names, 2)]))
    ratio = bands[1] / bands[0]
    assert len(ratio) == 3 and np.all((ratio > 2.5) & (ratio < 6.0)), ratio
