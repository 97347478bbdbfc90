"""Plane homographies, footprints, GSD and polygon overlaps against closed forms and ray casting."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from synthetic_world import HEIGHT, WIDTH, look_at, straight_down_camera

from rigsfm.core.ground import (
    MAX_COVERAGE_CELLS,
    coverage,
    footprint,
    footprints,
    ground_from_image,
    image_from_plane,
    image_to_plane,
    pairwise_overlaps,
    undistort_pixels,
)
from rigsfm.core.polygons import (
    clip_polygon,
    convex_pieces,
    intersect_polygons,
    intersection_area,
    is_convex,
    polygon_area,
    triangulate_polygon,
)


def tilted_camera(model: str = "OPENCV", centre=(15.0, 0.0, 3.5), target=(0.0, 1.0, 0.0)) -> pycolmap.Image:
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, model, 1.0, WIDTH, HEIGHT)
    camera.params = {"OPENCV": [1800.0, 1795.0, 409.0, 306.0, -0.05, 0.3, 0.001, -0.0005],
                     "PINHOLE": [1800.0, 1795.0, 409.0, 306.0]}[model]
    rec.add_camera_with_trivial_rig(camera)
    rec.add_image_with_trivial_frame(pycolmap.Image(image_id=1, name="rig01/narrow/f0.png", camera_id=1),
                                     look_at(np.array(centre), np.array(target), roll_deg=1.0))
    return rec, rec.images[1]


@pytest.mark.parametrize("height", [0.0, 1.7])
def test_homography_and_ray_casting_agree_with_projection(height):
    rec, image = tilted_camera()
    rng = np.random.default_rng(0)
    xy = rng.uniform(-4, 4, (200, 2)) + [2.0, 1.0]
    world = np.c_[xy, np.full(len(xy), height)]
    in_cam = np.array([image.cam_from_world() * p for p in world])
    raw = image.camera.img_from_cam(in_cam)  # distorted COLMAP pixels
    inside = (raw[:, 0] > 0) & (raw[:, 0] < WIDTH) & (raw[:, 1] > 0) & (raw[:, 1] < HEIGHT)
    assert inside.sum() > 50
    back, valid = image_to_plane(image, raw[inside], height)
    assert valid.all()
    np.testing.assert_allclose(back, xy[inside], atol=1e-6)
    undistorted = undistort_pixels(image.camera, raw[inside])
    k = np.asarray(image.camera.calibration_matrix())
    np.testing.assert_allclose(undistorted, (in_cam[inside, :2] / in_cam[inside, 2:]) @ k[:2, :2].T + k[:2, 2], atol=1e-6)
    g = ground_from_image(image, height)
    mapped = np.c_[undistorted, np.ones(len(undistorted))] @ g.T
    assert (mapped[:, 2] > 0).all()
    np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], xy[inside], atol=1e-6)
    h = image_from_plane(image, height)
    np.testing.assert_allclose(np.linalg.inv(h) / np.linalg.inv(h)[2, 2], g / g[2, 2], rtol=1e-9, atol=1e-12)


def test_pixels_above_the_horizon_have_negative_w():
    rec, image = tilted_camera(target=(0.0, 0.0, 3.0))  # looking slightly down: horizon inside the image
    g = ground_from_image(image)
    top, bottom = np.array([WIDTH / 2, 1.0, 1.0]), np.array([WIDTH / 2, HEIGHT - 1.0, 1.0])
    assert (g @ top)[2] < 0 < (g @ bottom)[2]


def test_straight_down_footprint_is_the_image_rectangle():
    height, focal = 10.0, 1000.0
    image = straight_down_camera(height, focal).images[1]
    for plane in (0.0, 1.7):
        fp = footprint(image, plane)
        scale = (height - plane) / focal
        assert fp.area == pytest.approx(WIDTH * HEIGHT * scale**2, rel=1e-9)
        np.testing.assert_allclose(fp.polygon.min(axis=0), [-WIDTH / 2 * scale, -HEIGHT / 2 * scale], atol=1e-9)
        np.testing.assert_allclose(fp.centre, [0.0, 0.0], atol=1e-12)
        assert fp.gsd_mm_per_px == pytest.approx(1000 * scale, rel=1e-9)
        assert fp.gsd_mm_per_px_xy == pytest.approx((1000 * scale, 1000 * scale), rel=1e-9)
        assert fp.camera_height == pytest.approx(height - plane)
        assert fp.convex and not fp.clipped and polygon_area(fp.polygon) > 0


def test_gsd_of_a_tilted_camera_matches_finite_differences():
    rec, image = tilted_camera("PINHOLE")
    fp = footprint(image)
    depth = np.linalg.norm(np.r_[fp.centre, 0.0] - image.projection_center())
    view = np.asarray(image.viewing_direction())
    grazing = np.arcsin(-view[2])  # angle between the optical axis and the floor
    # across the view: depth / f; along it: depth / (f sin(grazing)) (centre pixel ~ principal point)
    assert fp.gsd_mm_per_px_xy[0] == pytest.approx(1000 * depth / 1800.0, rel=0.01)
    assert fp.gsd_mm_per_px_xy[1] == pytest.approx(1000 * depth / (1795.0 * np.sin(grazing)), rel=0.01)
    assert fp.gsd_mm_per_px == pytest.approx(np.sqrt(np.prod(fp.gsd_mm_per_px_xy)), rel=0.01)


def test_horizon_clips_the_footprint_at_max_depth():
    rec, image = tilted_camera("PINHOLE", target=(0.0, 0.0, 3.0))  # the horizon crosses the image
    fp = footprint(image, max_depth=60.0)
    assert fp.clipped and fp.convex
    depths = [(image.cam_from_world() * np.r_[p, 0.0])[2] for p in fp.polygon]
    assert max(depths) == pytest.approx(60.0, rel=1e-6)


def test_camera_looking_up_or_below_the_plane_has_no_footprint():
    _, up = tilted_camera(centre=(0.0, 0.0, 3.5), target=(10.0, 0.0, 20.0))
    assert footprint(up) is None
    assert footprint(straight_down_camera(1.5).images[1], height=1.7) is None


def test_barrel_distortion_bends_the_footprint_edges_inwards():
    """k1 r^2 + k2 r^4 < 0 at the corners (barrel): the undistorted border is pincushion-shaped."""
    rec, image = tilted_camera()
    assert not footprint(image).convex
    _, pinhole = tilted_camera("PINHOLE")
    assert footprint(pinhole).convex


def test_polygon_helpers():
    square = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], dtype=float)
    shifted = square + 1.0
    assert polygon_area(square) == 4.0 and polygon_area(square[::-1]) == -4.0
    np.testing.assert_allclose(polygon_area(clip_polygon(square, shifted)), 1.0)
    l_shape = np.array([[0, 0], [3, 0], [3, 1], [1, 1], [1, 3], [0, 3]], dtype=float)
    assert not is_convex(l_shape) and is_convex(square)
    tris = triangulate_polygon(l_shape)
    assert len(tris) == 4 and sum(polygon_area(t) for t in tris) == pytest.approx(5.0)
    assert sum(polygon_area(p) for p in convex_pieces(l_shape)) == pytest.approx(5.0)  # ear clipping
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    pincushion = np.c_[np.cos(angles), np.sin(angles)] * (1 - 0.1 * np.cos(4 * angles))[:, None]
    pieces = convex_pieces(pincushion)  # star-shaped from its centroid: a fan
    assert len(pieces) == 40 and all(is_convex(p) and polygon_area(p) > 0 for p in pieces)
    assert sum(polygon_area(p) for p in pieces) == pytest.approx(polygon_area(pincushion), rel=1e-12)


def inside(polygon: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Even-odd rule point-in-polygon."""
    result = np.zeros(len(pts), bool)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        crosses = (a[1] > pts[:, 1]) != (b[1] > pts[:, 1])
        x = a[0] + (pts[:, 1] - a[1]) * (b[0] - a[0]) / np.where(b[1] != a[1], b[1] - a[1], 1.0)
        result ^= crosses & (pts[:, 0] < x)
    return result


def raster_area(a, b, step=0.005):
    lo = np.minimum(a.min(0), b.min(0))
    hi = np.maximum(a.max(0), b.max(0))
    xs, ys = np.meshgrid(np.arange(lo[0], hi[0], step) + step / 2, np.arange(lo[1], hi[1], step) + step / 2)
    pts = np.c_[xs.ravel(), ys.ravel()]
    return np.count_nonzero(inside(a, pts) & inside(b, pts)) * step**2


@pytest.mark.parametrize("seed", range(4))
def test_intersection_of_non_convex_polygons(seed):
    rng = np.random.default_rng(seed)

    def star(centre):
        angles = np.sort(rng.uniform(0, 2 * np.pi, 14))
        return centre + np.c_[np.cos(angles), np.sin(angles)] * rng.uniform(0.5, 1.5, 14)[:, None]

    a, b = star(np.zeros(2)), star(rng.uniform(-0.7, 0.7, 2))
    pieces = intersect_polygons(a, b)
    area = sum(polygon_area(p) for p in pieces)
    assert not (is_convex(a) and is_convex(b))
    assert area == pytest.approx(raster_area(a, b), abs=0.01)
    assert intersection_area(a, b) == pytest.approx(area, abs=1e-9)  # Green's theorem, no clipping
    assert intersection_area(a, b + 10.0) == 0.0
    assert intersection_area(a, 0.1 * b) == pytest.approx(polygon_area(0.1 * b), rel=1e-9)  # nested


def test_overlaps_and_coverage_of_two_footprints():
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 1000.0, WIDTH, HEIGHT)
    camera.params = [1000.0, 1000.0, WIDTH / 2, HEIGHT / 2]
    rec.add_camera_with_trivial_rig(camera)
    rotation = np.diag([1.0, -1.0, -1.0])
    for image_id, x in ((1, 0.0), (2, 4.0)):  # two straight-down cameras 10 m up, 4 m apart: 8.12 x 6.17 m each
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ np.array([x, 0.0, 10.0]))
        rec.add_image_with_trivial_frame(pycolmap.Image(image_id=image_id, name=f"rig0{image_id}/narrow/f0.png",
                                                        camera_id=1), pose)
    prints = footprints(rec, "narrow")
    (overlap,) = pairwise_overlaps(prints)
    assert overlap.area == pytest.approx((8.12 - 4.0) * 6.17, rel=1e-9)
    assert pairwise_overlaps(prints, pieces=False)[0].area == pytest.approx(overlap.area, rel=1e-9)
    cov = coverage(prints, cell=0.02)
    assert cov.area_at_least(2) == pytest.approx(overlap.area, rel=0.01)
    assert cov.area_at_least(1) == pytest.approx(2 * 8.12 * 6.17 - overlap.area, rel=0.01)
    (outline,) = cov.outlines(2)
    assert polygon_area(outline) == pytest.approx(overlap.area, rel=0.02)


def test_ground_maps_are_json_ready():
    import json

    from rigsfm.run.world.frame import ground_maps

    rec = straight_down_camera(10.0)
    maps = ground_maps(rec, heights=(0.0, 1.7))
    (entries,) = maps.per_image.values()
    entries = json.loads(json.dumps(entries))
    assert [e["plane_height_m"] for e in entries] == [0.0, 1.7]
    assert entries[1]["gsd_mm_per_px"] == pytest.approx(8.3, rel=1e-9)
    assert entries[0]["footprint_area_m2"] == pytest.approx(WIDTH * HEIGHT * 0.01**2, rel=1e-9)
    g = np.array(entries[1]["ground_from_image"])
    xyw = g @ [WIDTH / 2 + 100, HEIGHT / 2, 1.0]
    np.testing.assert_allclose(xyw[:2] / xyw[2], [0.83, 0.0], atol=1e-12)
    assert maps.seen_twice_m2 == [0.0, 0.0] and maps.overlaps == {}


def test_coverage_of_footprints_far_apart_keeps_its_raster_small():
    """A network spread over hundreds of kilometres (a known length given in centimetres, a shape the images do
    not fix) made `rigsfm run` ask for an 11.3 TiB raster at the floor's 5 cm cells and end in an internal error:
    the cells grow where the footprints' span needs it, the area seen twice stays measured."""
    square = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]])
    near = {"a": square, "b": square + [50.0, 0.0]}  # 50 x 100 m seen twice
    for far in ([20e3, 0.0], [6e5, 2.6e4]):
        cov = coverage({**near, "c": square + far})
        assert cov.counts.size <= 1.01 * MAX_COVERAGE_CELLS
        if far[0] < 1e5:  # 0.32 m cells over 20 km
            assert cov.area_at_least(2) == pytest.approx(5000.0, rel=0.02)
