"""Floor matching through the plane-induced warp on images rendered from a textured floor (exact cameras)."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest
from synthetic_world import HEIGHT, WIDTH, ring

from rigsfm.core.errors import InputError
from rigsfm.run.world.floor import estimate_floor
from rigsfm.run.world.floor_matching import match_floor_points, plane_hits, triangulate_pairs

CELL = 0.01  # metres per texture pixel
HALF = 20.0  # the texture covers [-HALF, HALF]^2


def floor_texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    size = int(2 * HALF / CELL)
    texture = np.full((size, size), 128, np.uint8)
    for _ in range(9000):
        centre = tuple(int(v) for v in rng.integers(0, size, 2))
        cv2.circle(texture, centre, int(rng.integers(5, 40)), int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(texture, (0, 0), 1.5)


def render(image: pycolmap.Image, texture: np.ndarray) -> np.ndarray:
    """The floor z = 0 (truth frame = model frame here) seen by ``image``; grey where there is no floor."""
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = image.camera.cam_from_img(np.stack([xs.ravel(), ys.ravel()], axis=1))
    hits, ok = plane_hits(image, np.array([0.0, 0.0, 1.0]), 0.0, 100.0, rays)
    u = (hits[:, 0] + HALF) / CELL - 0.5
    v = (HALF - hits[:, 1]) / CELL - 0.5
    ok &= (u >= 0) & (u < texture.shape[1] - 1) & (v >= 0) & (v < texture.shape[0] - 1)
    map_x = np.where(ok, u, -1).reshape(HEIGHT, WIDTH).astype(np.float32)
    map_y = np.where(ok, v, -1).reshape(HEIGHT, WIDTH).astype(np.float32)
    return cv2.remap(texture, map_x, map_y, cv2.INTER_AREA, borderMode=cv2.BORDER_CONSTANT, borderValue=128)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    identity = pycolmap.Rigid3d()
    world = ring(seed=0, num_rigs=4, radius=12.0, floor_points=0, wall_points=0, box_points=0, pillar_points=0,
                 model_from_truth=identity)
    root = tmp_path_factory.mktemp("floor_images")
    texture = floor_texture()
    for image in world.reconstruction.images.values():
        path = root / image.name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), render(image, texture))
    return world, root


def test_warped_matching_triangulates_floor_points(scene):
    world, root = scene
    guess = np.array([0.0, 0.03, 1.0])  # 1.7 deg and 0.3 m off: a rough guess is enough
    matches = match_floor_points(world.reconstruction, root, guess / np.linalg.norm(guess), -0.3)
    assert len(matches) > 100
    assert len(matches.pairs) == 6  # 4 wide cameras round the floor: every pair sees a common part
    heights = matches.points[:, 2]
    assert np.median(np.abs(heights)) < 0.01
    assert np.mean(np.abs(heights) < 0.05) > 0.95


def test_estimate_floor_from_images_alone(scene):
    world, root = scene
    estimate = estimate_floor(world.reconstruction, root)
    fit = estimate.fit
    assert fit, fit
    assert estimate.why_matched.startswith("no floor in the sparse points") and estimate.rounds >= 1
    assert fit.points_by_source["matched"] == fit.num_points > 100
    for name, height in world.truth_heights.items():
        assert fit.camera_heights[name] == pytest.approx(height, abs=0.01)


def test_missing_images_are_an_input_error(scene, tmp_path):
    world, _ = scene
    with pytest.raises(InputError, match="cannot be read"):
        match_floor_points(world.reconstruction, tmp_path, np.array([0.0, 0.0, 1.0]), 0.0)


def test_triangulation_is_colmaps(scene):
    """All matches at once, as pycolmap.triangulate_point one at a time (noisy pixels: not the exact points)."""
    world, _ = scene
    image_i, image_j = (world.reconstruction.image(i) for i in sorted(world.reconstruction.images)[:2])
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-5, 5, (200, 2)), rng.uniform(0, 2, 200)]
    xy_i, xy_j = (np.asarray(im.camera.img_from_cam(points @ im.cam_from_world().rotation.matrix().T
                                                     + im.cam_from_world().translation)) + rng.normal(0, 1, (200, 2))
                  for im in (image_i, image_j))
    one_by_one = [pycolmap.triangulate_point(image_i.cam_from_world().matrix(), image_j.cam_from_world().matrix(),
                                             image_i.camera.cam_from_img(p), image_j.camera.cam_from_img(q))
                  for p, q in zip(xy_i, xy_j)]
    np.testing.assert_allclose(triangulate_pairs(image_i, image_j, xy_i, xy_j),
                               np.array([np.ravel(x) for x in one_by_one]), rtol=1e-9, atol=1e-9)
    assert np.abs(triangulate_pairs(image_i, image_j, xy_i, xy_j) - points).max() > 1e-3  # the noise shows
