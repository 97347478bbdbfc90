"""The synthetic arena: exact ground truth, homogeneous narrow views, SIFT-friendly wide views."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest
import yaml

from rigsfm.core.conventions import rotation_angle_deg
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.geometry import project_world
from rigsfm.core.rig import load_rigs
from rigsfm.synth import (
    SceneOptions,
    build_arena,
    make_rigs,
    render_clean,
    render_dataset,
    render_image,
)
from rigsfm.synth.render import pixel_rays, visible
from rigsfm.synth.scene import WALL, Bar, trace

OPTIONS = SceneOptions(image_scale=0.5, seed=0)


def project(camera, pose, points):
    """Pixels of world points, NaN where not seen (in front, where the lens model is monotonic)."""
    return project_world(camera, pose, points, margin_px=None)[0]


@pytest.fixture(scope="module")
def dataset(rendered):
    return rendered(OPTIONS)


@pytest.fixture(scope="module")
def gt(dataset):
    return dataset.load_ground_truth()


@pytest.fixture(scope="module")
def arena(dataset):
    scene = yaml.safe_load((dataset.root / "scene.yaml").read_text())
    return build_arena(OPTIONS).with_bar(_bar(scene["bar"]))


def _bar(spec):
    return Bar(np.array(spec["a"]), np.array(spec["b"]))


def _image(rec: pycolmap.Reconstruction, name: str) -> pycolmap.Image:
    return next(image for image in rec.images.values() if image.name == name)


def _read(dataset, name: str) -> np.ndarray:
    image = cv2.imread(str(dataset.images / name), cv2.IMREAD_UNCHANGED)
    assert image is not None, name
    return image


def _sample(image: np.ndarray, xy_colmap: np.ndarray) -> np.ndarray:
    """Bilinear image values at COLMAP pixel coordinates."""
    xy = (xy_colmap - 0.5).astype(np.float32)
    return cv2.remap(image.astype(np.float32), xy[:, :1], xy[:, 1:], cv2.INTER_LINEAR).ravel()


def test_dataset_layout_and_ground_truth_structure(dataset, gt):
    assert len(dataset.image_names) == 16
    for rig in range(1, 9):
        for sensor in ("wide", "narrow"):
            image = _read(dataset, f"rig{rig:02d}/{sensor}/frame0000.png")
            assert image.shape == (617, 812) and image.dtype == np.uint8
    assert (len(gt.rigs), len(gt.cameras), len(gt.frames), len(gt.images)) == (8, 16, 8, 16)
    assert sorted(image.name for image in gt.images.values()) == sorted(dataset.image_names)
    exact = {rig.name: rig for rig in load_rigs(dataset.rigs_exact)}
    for image in gt.images.values():
        rig_name, sensor, _ = image.name.split("/")
        camera = gt.cameras[image.camera_id]
        assert np.allclose(camera.params, exact[rig_name].camera(sensor).params, rtol=0, atol=1e-12)
        rig = gt.rigs[gt.frames[image.frame_id].rig_id]
        sensor_id = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, image.camera_id)
        assert rig.is_ref_sensor(sensor_id) == (sensor == "wide")
        if sensor == "narrow":
            wide = next(
                i
                for i in gt.images.values()
                if i.frame_id == image.frame_id and i.camera_id != image.camera_id
            )
            expected = exact[rig_name].narrow_from_wide * wide.cam_from_world()
            assert np.abs(image.cam_from_world().matrix() - expected.matrix()).max() < 1e-12
            assert (
                np.abs(
                    rig.sensor_from_rig(sensor_id).matrix() - exact[rig_name].narrow_from_wide.matrix()
                ).max()
                < 1e-12
            )


def test_wide_cameras_on_circle_and_narrow_views_inside_homogeneous_disc(gt):
    azimuths = []
    for image in gt.images.values():
        centre = image.projection_center()
        if "/wide/" in image.name:
            assert abs(np.hypot(centre[0], centre[1]) - OPTIONS.radius) < 1e-9
            assert 3.0 <= centre[2] <= 4.0
            azimuths.append(np.degrees(np.arctan2(centre[1], centre[0])))
            continue
        camera = gt.cameras[image.camera_id]
        world_from_cam = image.cam_from_world().inverse().matrix()
        axis = world_from_cam[:, 2]
        hit = centre - centre[2] / axis[2] * axis
        assert np.hypot(hit[0], hit[1]) < 7.0  # the optical axis hits the centre disc (radius 11 m)
        corners = np.array(
            [
                [0.5, 0.5],
                [camera.width - 0.5, 0.5],
                [0.5, camera.height - 0.5],
                [camera.width - 0.5, camera.height - 0.5],
            ]
        )
        rays = camera.cam_ray_from_img(corners) @ world_from_cam[:, :3].T
        ground = centre - (centre[2] / rays[:, 2])[:, None] * rays
        assert np.all(rays[:, 2] < 0) and np.all(np.hypot(ground[:, 0], ground[:, 1]) < OPTIONS.centre_radius)
    steps = np.diff(np.sort(np.mod(azimuths, 360.0)))
    assert np.allclose(steps, 45.0, atol=1e-9)


def test_rigs_yaml_perturbation_within_bands(dataset):
    noisy, exact = load_rigs(dataset.rigs), load_rigs(dataset.rigs_exact)
    assert [r.name for r in noisy] == [r.name for r in exact] == [f"rig{i:02d}" for i in range(1, 9)]
    for a, b in zip(noisy, exact):
        for sensor in ("wide", "narrow"):
            pa, pb = np.array(a.camera(sensor).params), np.array(b.camera(sensor).params)
            rel_focal = np.abs(pa[:2] / pb[:2] - 1)
            assert np.all((rel_focal >= 0.0005 - 1e-12) & (rel_focal <= 0.0015 + 1e-12)), rel_focal
            assert np.all((np.abs(pa[2:4] - pb[2:4]) >= 0.2) & (np.abs(pa[2:4] - pb[2:4]) <= 0.8))
            assert 0 < np.abs(pa[4] - pb[4]) <= 0.0006 and np.abs(pa[5] - pb[5]) <= 0.0003
            # The distortion error alone moves no image point by more than a pixel.
            camera = b.camera(sensor)
            distortion_only = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                                              params=np.concatenate([pb[:4], pa[4:]]))
            corners = np.array([[0.5, 0.5], [camera.width - 0.5, camera.height - 0.5],
                                [0.5, camera.height - 0.5], [camera.width / 2, camera.height / 2]])
            rays = camera.cam_from_img(corners)
            rays3 = np.column_stack([rays, np.ones(len(rays))])
            shift = np.linalg.norm(distortion_only.img_from_cam(rays3) - corners, axis=1)
            assert 0 < shift.max() < 1.0, shift
        angle = rotation_angle_deg(a.narrow_from_wide.rotation.matrix(), b.narrow_from_wide.rotation.matrix())
        assert 0.05 - 1e-9 <= angle <= 0.1 + 1e-9
        dt = np.abs(np.array(a.narrow_from_wide.translation) - np.array(b.narrow_from_wide.translation))
        assert np.all(dt <= 0.001) and dt.max() > 0
        baseline = np.linalg.norm(b.narrow_from_wide.inverse().translation)
        assert abs(baseline - OPTIONS.baseline) < 1e-12


def test_sift_many_wide_features_few_narrow_and_neighbour_matches(dataset):
    sift = cv2.SIFT_create()
    wide1, desc1 = sift.detectAndCompute(_read(dataset, "rig01/wide/frame0000.png"), None)
    wide2, desc2 = sift.detectAndCompute(_read(dataset, "rig02/wide/frame0000.png"), None)
    narrow = sift.detect(_read(dataset, "rig01/narrow/frame0000.png"), None)
    assert len(wide1) > 1000 and len(wide2) > 1000
    assert len(narrow) < 30
    assert _read(dataset, "rig01/narrow/frame0000.png").std() < 5.0
    pairs = cv2.BFMatcher().knnMatch(desc1, desc2, k=2)
    good = [m for m, n in pairs if m.distance < 0.8 * n.distance]
    p1 = np.float32([wide1[m.queryIdx].pt for m in good])
    p2 = np.float32([wide2[m.trainIdx].pt for m in good])
    _, inliers = cv2.findFundamentalMat(p1, p2, cv2.FM_RANSAC, 1.0, 0.999)
    assert len(good) > 300 and int(inliers.sum()) > 250


def test_wall_texture_appears_at_pixels_predicted_by_ground_truth(dataset, gt, arena):
    """Texture differences between wall points 2 px apart match the image best with zero pixel shift."""
    rng = np.random.default_rng(1)
    tex, radius = arena.textures.wall, OPTIONS.wall_radius
    for name in ("rig01/wide/frame0000.png", "rig04/wide/frame0000.png"):
        image = _image(gt, name)
        camera, pose = gt.cameras[image.camera_id], image.cam_from_world()
        pixels = _read(dataset, name)
        world_from_cam = pose.inverse().matrix()
        kind = trace(arena, world_from_cam[:, 3], pixel_rays(camera) @ world_from_cam[:, :3].T).kind
        interior = cv2.erode((kind.reshape(pixels.shape) == WALL).astype(np.uint8), np.ones((7, 7), np.uint8))
        theta, z = rng.uniform(0, 2 * np.pi, 30000), rng.uniform(0.5, 15.5, 30000)
        points = np.stack([radius * np.cos(theta), radius * np.sin(theta), z], axis=1)
        xy = project(camera, pose, points)
        keep = np.all(np.isfinite(xy), axis=1) & np.all(xy > 4, axis=1)
        keep &= (xy[:, 0] < camera.width - 4) & (xy[:, 1] < camera.height - 4)
        keep[keep] &= interior[xy[keep, 1].astype(int), xy[keep, 0].astype(int)] > 0
        theta, z, points, xy = theta[keep], z[keep], points[keep], xy[keep]
        assert len(points) > 5000
        distance = np.linalg.norm(points - image.projection_center(), axis=1)
        dtheta = 2.0 * distance / camera.focal_length_x / radius
        xy2 = project(
            camera, pose, np.stack([radius * np.cos(theta + dtheta), radius * np.sin(theta + dtheta), z], 1)
        )
        incidence = np.abs(
            np.einsum(
                "ij,ij->i",
                (points - image.projection_center()) / distance[:, None],
                np.stack([np.cos(theta), np.sin(theta), 0 * theta], 1),
            )
        )
        footprint = distance / camera.focal_length_x / np.sqrt(incidence)
        expected = tex.sample((2 * np.pi - theta - dtheta) * radius, OPTIONS.wall_height - z, footprint)
        expected -= tex.sample((2 * np.pi - theta) * radius, OPTIONS.wall_height - z, footprint)
        scores = {}
        for shift in [(0, 0), (0.5, 0), (-0.5, 0), (0, 0.5), (0, -0.5), (1, 0), (0, 1)]:
            observed = _sample(pixels, xy2 + shift) - _sample(pixels, xy + shift)
            scores[shift] = np.corrcoef(observed, expected)[0, 1]
        assert scores[(0, 0)] > 0.8, scores
        assert max(scores, key=scores.get) == (0, 0), scores


def test_bar_marker_found_at_projected_pixel_in_close_up(gt, arena):
    """A distorted wide camera straight above a bar end: the marker's centroid lands on its projection."""
    camera = gt.cameras[1]
    end = arena.bar.a
    world_from_cam = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # looking straight down
    for offset in ([0.0, 0.0], [2.0, 1.5], [-2.2, -1.4]):  # centre, then near two corners (distortion)
        centre = end + np.array([-offset[0], offset[1], 4.0])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(world_from_cam.T), -world_from_cam.T @ centre)
        clean = render_clean(arena, camera, pose) * 255
        predicted = project(camera, pose, end[None])[0]
        assert 30 < predicted[0] < camera.width - 30 and 30 < predicted[1] < camera.height - 30
        # Exact image of the bright disc: the projected outline; its area centroid is where the image's
        # centroid must be (distortion shifts it from the centre's projection by a few tenths of a pixel).
        phi = np.linspace(0, 2 * np.pi, 721)[:-1]
        outline = end + arena.bar.marker_radius * np.stack([np.cos(phi), np.sin(phi), 0 * phi], axis=1)
        px, py = project(camera, pose, outline).T
        cross = px * np.roll(py, -1) - np.roll(px, -1) * py
        area = cross.sum() / 2
        expected = np.array(
            [((px + np.roll(px, -1)) * cross).sum(), ((py + np.roll(py, -1)) * cross).sum()]
        ) / (6 * area)
        x, y = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
        radius_px = 0.3 / 4.0 * camera.focal_length_x  # between the bright disc and the dark ring's edge
        window = np.hypot(x - predicted[0], y - predicted[1]) < radius_px
        weight = np.clip(clean - 128, 0, None) * window
        centroid = np.array([(weight * x).sum(), (weight * y).sum()]) / weight.sum()
        assert np.linalg.norm(centroid - expected) < 0.1, (offset, centroid, expected, predicted)
        assert np.linalg.norm(expected - predicted) < 0.5


def test_known_length_and_camera_distance_match_ground_truth(dataset, gt):
    scale = yaml.safe_load(dataset.scale.read_text())
    (distance,) = scale["camera_distance"]
    centres = {image.name.rsplit("/", 1)[0]: image.projection_center() for image in gt.images.values()}
    assert (distance["a"], distance["b"]) == ("rig01/wide", "rig05/wide")
    assert abs(distance["meters"] - np.linalg.norm(centres["rig01/wide"] - centres["rig05/wide"])) < 1e-9
    (bar,) = scale["known_length"]
    assert bar["meters"] == 2.0 and len(bar["observations"]) == 2
    ends = {}
    for key in ("a", "b"):
        origins, directions = [], []
        for obs in bar["observations"]:
            image = _image(gt, obs["image"])
            camera = gt.cameras[image.camera_id]
            assert 0 < obs[key][0] < camera.width and 0 < obs[key][1] < camera.height
            ray = camera.cam_ray_from_img(np.array([obs[key]], dtype=np.float64))[0]
            world_from_cam = image.cam_from_world().inverse().matrix()
            origins.append(world_from_cam[:, 3])
            directions.append(world_from_cam[:, :3] @ ray)
        # Midpoint of the shortest segment between the two rays.
        (o1, o2), (d1, d2) = origins, directions
        s, t = np.linalg.lstsq(np.stack([d1, -d2], axis=1), o2 - o1, rcond=None)[0]
        ends[key] = (o1 + s * d1 + o2 + t * d2) / 2
        assert np.linalg.norm((o1 + s * d1) - (o2 + t * d2)) < 1e-6
        assert abs(ends[key][2]) < 1e-3  # lies on the ground
    assert abs(np.linalg.norm(ends["a"] - ends["b"]) - 2.0) < 1e-3


def test_two_rig_arc_exact_calibration_and_several_frames(tmp_path):
    options = SceneOptions(
        num_rigs=2, arc_deg=60.0, image_scale=0.25, calibration_noise=False, frames_per_rig=2
    )
    data = render_dataset(tmp_path / "arc", options)
    rec = data.load_ground_truth()
    assert (len(rec.rigs), len(rec.frames), len(rec.images)) == (2, 4, 8)
    centres = {image.name: image.projection_center() for image in rec.images.values()}
    a, b = centres["rig01/wide/frame0000.png"], centres["rig02/wide/frame0000.png"]
    angle = np.degrees(np.arccos(np.dot(a[:2], b[:2]) / np.linalg.norm(a[:2]) / np.linalg.norm(b[:2])))
    assert abs(angle - 60.0) < 1e-9
    assert np.allclose(centres["rig01/wide/frame0001.png"], a, atol=1e-12)
    assert data.rigs.read_text() == data.rigs_exact.read_text()
    scale = yaml.safe_load(data.scale.read_text())
    assert (scale["camera_distance"][0]["a"], scale["camera_distance"][0]["b"]) == (
        "rig01/wide",
        "rig02/wide",
    )
    first, second = (_read(data, f"rig01/wide/frame000{i}.png").astype(float) for i in (0, 1))
    assert first.shape == (308, 406)
    assert 0.5 < np.abs(first - second).mean() < 3.0  # same view, independent noise
    with pytest.raises(WorkspaceError):
        render_dataset(tmp_path / "arc", options)


def test_textured_centre_gives_narrow_features():
    options = SceneOptions(image_scale=0.5, textured_centre=True)
    rig = make_rigs(options)[0]
    image = render_image(build_arena(options), rig.narrow, rig.narrow_from_world, np.random.default_rng(0))
    assert len(cv2.SIFT_create().detect(image, None)) > 300


def test_pillars_occlude_the_wall(arena, gt):
    image = _image(gt, "rig01/wide/frame0000.png")
    camera, pose = gt.cameras[image.camera_id], image.cam_from_world()
    centre = image.projection_center()
    occluders = 0
    for pillar in arena.pillars:
        direction = np.array([pillar.x, pillar.y, 2.0]) - centre
        direction /= np.linalg.norm(direction)
        front = np.array([pillar.x, pillar.y, 2.0]) - pillar.radius / np.hypot(*direction[:2]) * direction
        # The wall point on the same ray, behind the pillar.
        b, c = 2 * centre[:2] @ direction[:2], centre[:2] @ centre[:2] - OPTIONS.wall_radius**2
        a = direction[:2] @ direction[:2]
        wall = centre + (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a) * direction
        if not visible(arena, camera, pose, front[None], margin=2)[0]:
            continue
        occluders += 1
        assert np.allclose(project(camera, pose, wall[None]), project(camera, pose, front[None]), atol=1e-6)
        assert not visible(arena, camera, pose, wall[None])[0]
    assert occluders >= 1


def test_textures_are_shared_between_processes_through_the_cache_folder(tmp_path, monkeypatch):
    """RIGSFM_TEXTURE_CACHE: the first process makes the arrays and leaves them whole in the folder; a later one
    reads back the very same arrays without making them; unset, every call makes them."""
    from rigsfm.synth.scene import TEXTURE_CACHE_ENV, _shared_arrays

    made = []

    def make():
        made.append(1)
        return np.random.default_rng(3).random((40, 30)).astype(np.float32), np.arange(5.0)

    monkeypatch.setenv(TEXTURE_CACHE_ENV, str(tmp_path / "cache"))
    first = _shared_arrays("k", make)
    again = _shared_arrays("k", make)
    assert len(made) == 1 and [p.name for p in (tmp_path / "cache").iterdir()] == ["k.npz"]
    for a, b in zip(first, again, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    entry = tmp_path / "cache" / "k.npz"
    entry.write_bytes(entry.read_bytes()[:200])  # unreadable (truncated): made again and replaced
    _shared_arrays("k", make)
    assert len(made) == 2 and np.array_equal(_shared_arrays("k", make)[0], first[0]) and len(made) == 2
    monkeypatch.delenv(TEXTURE_CACHE_ENV)
    _shared_arrays("k", make)
    assert len(made) == 3


def test_ray_cull_by_sectors_picks_exactly_the_rays_of_its_definition():
    """rigsfm.synth.scene._rays_towards tests only the rays of the azimuth sectors around an object; it must return
    the very indices that testing every ray gives (objects behind the +-pi seam, near and far, around the origin)."""
    from rigsfm.synth.scene import _rays_towards, _sectors

    rng = np.random.default_rng(0)
    azimuth = np.concatenate([rng.uniform(-np.pi, np.pi, 200_000), [-np.pi, np.pi, 0.0, np.nan]])
    sectors = _sectors(azimuth)
    origin = np.array([1.0, -2.0, 1.5])
    objects = [(-20.0, -2.0 + 1e-9, 0.05), (-20.0, -2.1, 0.5), (-20.0, -1.9, 0.5),  # at the seam, either side
               (15.0, 3.0, 2.0), (1.0, -1.0, 0.9), (1.0, -1.0, 1.1), (1.0, 10.0, 0.3)]  # near (and around), far
    objects += [(x, y, abs(r) / 10) for x, y, r in rng.uniform(-20, 20, (40, 3))]
    for x, y, reach in objects:
        dist = np.hypot(x - origin[0], y - origin[1])
        expected = (np.arange(len(azimuth)) if dist <= reach + 1e-6 else np.flatnonzero(
            np.abs(np.mod(azimuth - np.arctan2(y - origin[1], x - origin[0]) + np.pi, 2 * np.pi) - np.pi)
            <= np.arcsin(reach / dist) + 1e-3))
        np.testing.assert_array_equal(_rays_towards(origin, azimuth, sectors, x, y, reach), expected)
