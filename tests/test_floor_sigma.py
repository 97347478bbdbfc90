"""The floor's reported uncertainty against a known truth: the points of one image pair share that pair's pose error
(grouped_plane_precision), and the floor is fitted again once the model is adjusted again (refit_floor)."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from synthetic_world import HEIGHT, WIDTH, add_hybrid_rig, look_at, ring

from rigsfm.run.adjustment.result import JointCovariance
from rigsfm.run.options import WorldOptions
from rigsfm.run.world.floor import FloorEstimate, with_pose_uncertainty
from rigsfm.run.world.floor_fit import fit_floor, grouped_plane_precision, plane_precision
from rigsfm.run.world.floor_matching import FloorMatches, PairMatches
from rigsfm.run.world.floor_model import fit_plane
from rigsfm.run.world.floor_poses import pose_floor_covariance
from rigsfm.run.world.frame import locate_world

# A crowd run's floor: 12 image pairs' patches round the arena, three of them holding most points (benchmarks/README.md)
PATCH_SIZES = (90, 60, 40, 10, 8, 8, 6, 6, 5, 5, 4, 4)
CAMERAS = np.array([[6.0 * np.cos(a), 6.0 * np.sin(a), 3.5] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])


def crowd_floor(rng: np.random.Generator, pair_sigma: float, point_sigma: float = 0.005):
    """Floor points (truth z = 0) of image pairs whose pose errors lift each pair's patch by N(0, pair_sigma)."""
    points, groups = [], []
    for g, size in enumerate(PATCH_SIZES):
        angle = 2 * np.pi * g / len(PATCH_SIZES) + rng.uniform(-0.2, 0.2)
        centre = 3.0 * np.array([np.cos(angle), np.sin(angle)])
        xy = centre + rng.uniform(-0.8, 0.8, (size, 2))
        z = rng.normal(0.0, pair_sigma) + rng.normal(0.0, point_sigma, size)
        points.append(np.c_[xy, z])
        groups += [f"pair{g}"] * size
    return np.vstack(points), np.array(groups)


def coverage(pair_sigma: float, trials: int = 200):
    """Fraction of trials whose tilt, and of cameras (over all trials) whose height, lie within the 95 % band of each
    sigma (the height's: the largest over the cameras, what summary.json reports): (grouped tilt, grouped height,
    scatter tilt, scatter height)."""
    rng = np.random.default_rng(5)
    inside = np.zeros(4)
    for _ in range(trials):
        points, groups = crowd_floor(rng, pair_sigma)
        normal, offset = fit_plane(points)
        normal, offset = (-normal, -offset) if normal[2] < 0 else (normal, offset)
        tilt = np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0)))
        height_error = np.abs(CAMERAS @ normal + offset - 3.5)
        grouped = grouped_plane_precision(points, groups, normal, offset, CAMERAS)
        r = points @ normal + offset
        scatter_tilt, scatter_height = plane_precision(points, normal, float(np.sqrt(np.mean(r**2))), CAMERAS)
        inside += [tilt <= 2.45 * grouped["normal_sigma_deg"], np.mean(height_error <= 1.96 * grouped["height_sigma"]),
                   tilt <= 2.45 * scatter_tilt, np.mean(height_error <= 1.96 * scatter_height)]
    return inside / trials


def test_a_sigma_with_the_pairs_shared_error_covers_the_tilt_and_the_heights():
    """Pairs lifted by 2 cm each (the rendered crowds' per-pair offsets were -39..+32 mm), 5 mm point scatter: the
    scatter's sigma (every point independent) covers the tilt in ~10 % of trials and a camera's height in ~30 %; the
    grouped one both in ~97 % (a 95 % band)."""
    grouped_tilt, grouped_height, scatter_tilt, scatter_height = coverage(pair_sigma=0.02)
    assert grouped_tilt >= 0.9 and grouped_height >= 0.9, (grouped_tilt, grouped_height)
    assert scatter_tilt < 0.3 and scatter_height < 0.5, (scatter_tilt, scatter_height)


def test_without_shared_error_the_grouped_sigma_is_the_scatters():
    rng = np.random.default_rng(1)
    points, groups = crowd_floor(rng, pair_sigma=0.0)
    normal, offset = fit_plane(points)
    grouped = grouped_plane_precision(points, groups, normal, offset, CAMERAS)
    r = points @ normal + offset
    scatter_tilt, scatter_height = plane_precision(points, normal, float(np.sqrt(np.mean(r**2))), CAMERAS)
    assert grouped["num_groups"] == len(PATCH_SIZES)
    assert grouped["effective_groups"] == pytest.approx(sum(PATCH_SIZES) ** 2 / sum(n**2 for n in PATCH_SIZES))
    assert grouped["normal_sigma_deg"] == pytest.approx(scatter_tilt, rel=0.25)
    assert grouped["height_sigma"] == pytest.approx(scatter_height, rel=0.25)
    assert grouped["group_sigma"] < 0.002 and grouped["point_sigma"] == pytest.approx(0.005, rel=0.15)


def test_fewer_than_four_pairs_cannot_show_their_shared_error():
    rng = np.random.default_rng(2)
    points, groups = crowd_floor(rng, pair_sigma=0.02)
    keep = np.isin(groups, ["pair0", "pair1", "pair2"])
    normal, offset = fit_plane(points[keep])
    grouped = grouped_plane_precision(points[keep], groups[keep], normal, offset, CAMERAS)
    assert grouped["num_groups"] == 3 and np.isinf(grouped["normal_sigma_deg"])


def moved(reconstruction: pycolmap.Reconstruction) -> pycolmap.Sim3d:
    """Move the whole model rigidly (the narrow stage's second adjustment moves the network in the first's gauge)."""
    angle = np.radians(0.2)
    rotation = pycolmap.Rotation3d(np.array([np.sin(angle / 2), 0.0, 0.0, np.cos(angle / 2)]))
    transform = pycolmap.Sim3d(1.0, rotation, np.array([0.01, -0.02, 0.04]))
    reconstruction.transform(transform)
    return transform


def test_the_floor_fitted_again_fits_the_moved_model():
    """A floor found before the model moves, applied after it (what the pipeline did before the refit), puts the
    cameras centimetres off their heights; fitted again, they are where they are."""
    world = ring(seed=20)
    rec = world.reconstruction
    result = locate_world(rec, None, None, ["rig01"], WorldOptions())
    moved(rec)
    stale = pycolmap.Reconstruction(rec)
    result.apply(stale)
    stale_error = max(abs(stale.find_image_with_name(n).projection_center()[2] - h)
                      for n, h in world.truth_heights.items())
    assert stale_error > 0.02  # the check below can fail
    result.refit(rec, None)
    result.apply(rec)
    for name, height in world.truth_heights.items():
        assert rec.find_image_with_name(name).projection_center()[2] == pytest.approx(height, abs=3e-3)
    floor = result.summary().floor
    assert floor["refitted_after_narrow_adjustment"] is True
    assert floor["normal_sigma_deg"] >= floor["scatter_normal_sigma_deg"]


def test_a_narrow_cameras_height_sigma_adds_its_own_vertical_uncertainty():
    world = ring(seed=20)
    rec = world.reconstruction
    result = locate_world(rec, None, None, ["rig01"], WorldOptions())
    result.apply(rec)
    # 10 mm along the camera's x and z, 20 mm along its y (down, ~vertical for a camera looking slightly down)
    own = {name: SimpleNamespace(centre_covariance_mm2=np.diag([100.0, 400.0, 100.0])) for name in world.truth_heights}
    result.set_narrow_heights(rec, own)
    heights = result.summary().floor["narrow_camera_heights"]
    assert sorted(heights) == sorted(n for n in world.truth_heights if "/narrow/" in n)
    for name, entry in heights.items():
        assert entry["height_m"] == pytest.approx(world.truth_heights[name], abs=3e-3)
        assert 0.015 < entry["own_sigma_m"] < 0.020
        assert 0 < entry["floor_sigma_m"] <= result.estimate.fit.height_sigma
        assert entry["sigma_m"] == pytest.approx(np.hypot(entry["floor_sigma_m"], entry["own_sigma_m"]))
    # a camera the fit holds no sigma for: null, not NaN (summary.json is read by strict JSON parsers)
    name = sorted(heights)[0]
    del result.estimate.fit.camera_height_sigmas[name]
    result.set_narrow_heights(rec, own)
    entry = result.summary().floor["narrow_camera_heights"][name]
    assert entry["floor_sigma_m"] is None and "sigma_m" not in entry and entry["own_sigma_m"] > 0
    json.dumps(result.summary().floor, allow_nan=False)
    # where the poses, moving the camera and the floor together, say more than the floor's and its own parts: theirs
    fit = result.estimate.fit
    result.estimate = replace(result.estimate, fit=replace(fit, pose_camera_height_sigmas={n: 0.05 for n in heights}))
    result.set_narrow_heights(rec, own)
    for entry in result.summary().floor["narrow_camera_heights"].values():
        assert entry["pose_sigma_m"] == pytest.approx(np.hypot(0.05, fit.scatter_height_sigma))
        assert entry.get("sigma_m", entry["pose_sigma_m"]) == entry["pose_sigma_m"]


def test_floor_matches_are_triangulated_again_with_the_new_poses():
    world = ring(seed=3)
    rec = world.reconstruction
    image_i = rec.find_image_with_name("rig01/wide/frame0000.png")
    image_j = rec.find_image_with_name("rig02/wide/frame0000.png")
    truth = np.array([world.model_from_truth * np.array([x, y, 0.0]) for x, y in ((0, 0), (2, 1), (-3, 2), (1, -4))])
    xy = [image.camera.img_from_cam(np.array([image.cam_from_world() * p for p in truth]))
          for image in (image_i, image_j)]
    matches = FloorMatches(truth, {(image_i.name, image_j.name): 4}, [PairMatches(image_i.name, image_j.name, *xy)])
    assert matches.groups() == [(image_i.name, image_j.name)] * 4
    transform = moved(rec)
    points, groups = matches.triangulated_in(rec)
    np.testing.assert_allclose(points, np.array([transform * p for p in truth]), atol=1e-6)
    assert groups == matches.groups()


def ring_floor_matches(world, rng: np.random.Generator, pairs=((1, 2), (2, 3), (3, 4), (5, 6), (7, 8))) -> FloorMatches:
    """Floor points (truth z = 0) seen by both wide images of each pair of rigs, as floor matches (exact pixels)."""
    rec = world.reconstruction
    matches, points = [], []
    for a, b in pairs:
        images = [rec.find_image_with_name(f"rig{k:02d}/wide/frame0000.png") for k in (a, b)]
        truth = np.c_[rng.uniform(-8, 8, (400, 2)), np.zeros(400)]
        model = np.array([world.model_from_truth * p for p in truth])
        xy, seen = [], np.ones(len(model), bool)
        for image in images:
            in_cam = np.array([image.cam_from_world() * p for p in model])
            seen &= in_cam[:, 2] > 0
            pixels = image.camera.img_from_cam(in_cam)
            seen &= (pixels[:, 0] > 0) & (pixels[:, 0] < image.camera.width) & (pixels[:, 1] > 0) \
                & (pixels[:, 1] < image.camera.height)
            xy.append(pixels)
        matches.append(PairMatches(images[0].name, images[1].name, xy[0][seen], xy[1][seen]))
        points.append(model[seen])
    return FloorMatches(np.vstack(points), {}, matches)


def frames_covariance(rec: pycolmap.Reconstruction, mode: np.ndarray | None = None) -> JointCovariance:
    frames = sorted(rec.reg_frame_ids())
    keys = tuple(("frame", f) for f in frames)
    offsets = {key: (6 * k, 6) for k, key in enumerate(keys)}
    covariance = np.outer(mode, mode) if mode is not None else np.eye(6 * len(frames)) * 1e-8
    return JointCovariance(keys, offsets, covariance, 1.0, "posterior")


def test_the_poses_covariance_tilts_the_floor_but_not_a_rotation_of_the_whole_network():
    """One frame's rotation error (1e-4 rad on each axis) tilts the floor relative to the cameras; the whole network
    turned together (every frame by the same world rotation: the gauge) moves floor and cameras alike: no tilt."""
    world = ring(seed=4)
    rec = world.reconstruction
    matches = ring_floor_matches(world, np.random.default_rng(0))
    fit = fit_floor(rec, extra_points=matches.points, extra_groups=matches.groups())
    assert fit and fit.points_by_source["matched"] > 500
    frames = sorted(rec.reg_frame_ids())
    one = np.zeros(6 * len(frames))
    one[6:9] = 1e-4  # the second frame's rotation
    tilt, _ = pose_floor_covariance(rec, matches, fit.normal, fit.offset, fit.threshold, frames_covariance(rec, one))
    assert np.sqrt(np.linalg.eigvalsh(tilt).max()) > 1e-6
    theta = np.array([3e-4, -2e-4, 1e-4])  # the same world rotation of every frame: w = -R theta, dt = 0
    whole = np.concatenate([np.r_[-rec.frame(f).rig_from_world.rotation.matrix() @ theta, np.zeros(3)] for f in frames])
    tilt, _ = pose_floor_covariance(rec, matches, fit.normal, fit.offset, fit.threshold, frames_covariance(rec, whole))
    assert np.sqrt(np.linalg.eigvalsh(tilt).max()) < 1e-8


def textured_ground(seed: int = 0, num_rigs: int = 8, points: int = 1500) -> pycolmap.Reconstruction:
    """Rigs round a featureless centre whose floor is only the sparse points of the textured ring about it (the
    rendered ``plain``/``flat`` networks' floors: benchmarks/README.md), each point observed with its exact pixels in
    every wide image that sees it (tracks of 2 to 8 views, as SfM's), none matched."""
    rng = np.random.default_rng(seed)
    radius = np.sqrt(rng.uniform(11.0**2, 26.0**2, points))
    angle = rng.uniform(0, 2 * np.pi, points)
    floor = np.c_[radius * np.cos(angle), radius * np.sin(angle), np.zeros(points)]
    poses, observed = [], []
    for index in range(num_rigs):
        a = 2 * np.pi * index / num_rigs
        centre = np.array([15.0 * np.cos(a), 15.0 * np.sin(a), 3.5 + rng.uniform(-0.25, 0.25)])
        pose = look_at(centre, np.array([0.0, 0.0, -3.0]), rng.normal(0, 0.5))
        in_cam = np.array([pose * p for p in floor])
        xy = 450.0 * in_cam[:, :2] / in_cam[:, 2:] + [WIDTH / 2, HEIGHT / 2]
        poses.append(pose)
        observed.append((in_cam[:, 2] > 0) & (xy[:, 0] > 0) & (xy[:, 0] < WIDTH) & (xy[:, 1] > 0) & (xy[:, 1] < HEIGHT))
        observed[-1] = observed[-1], xy
    rec = pycolmap.Reconstruction()
    seen = np.sum([o for o, _ in observed], axis=0) >= 2
    index_in = []
    for index, (pose, (o, xy)) in enumerate(zip(poses, observed)):
        keep = o & seen
        wide = pycolmap.Camera.create_from_model_name(2 * index + 1, "PINHOLE", 450.0, WIDTH, HEIGHT)
        wide.params = [450.0, 450.0, WIDTH / 2, HEIGHT / 2]
        narrow = pycolmap.Camera.create_from_model_name(2 * index + 2, "PINHOLE", 1800.0, WIDTH, HEIGHT)
        narrow.params = [1800.0, 1800.0, WIDTH / 2, HEIGHT / 2]
        add_hybrid_rig(rec, index + 1, f"rig{index + 1:02d}", wide, narrow, pycolmap.Rigid3d(), pose,
                       {"wide": list(xy[keep])})
        index_in.append(np.cumsum(keep) - 1)
    for k in np.flatnonzero(seen):
        track = pycolmap.Track()
        for index, (o, _) in enumerate(observed):
            if o[k]:
                track.add_element(2 * index + 1, int(index_in[index][k]))
        rec.add_point3D(floor[k] + [0.0, 0.0, rng.normal(0, 0.005)], track, np.zeros(3, np.uint8))  # the points' scatter
    return rec


def per_frame_covariance(rec: pycolmap.Reconstruction, rotation: float, translation: float) -> JointCovariance:
    frames = sorted(rec.reg_frame_ids())
    keys = tuple(("frame", f) for f in frames)
    diagonal = np.tile(np.r_[[rotation**2] * 3, [translation**2] * 3], len(frames))
    return JointCovariance(keys, {key: (6 * k, 6) for k, key in enumerate(keys)}, np.diag(diagonal), 1.0, "posterior")


def test_a_floor_of_sparse_points_alone_carries_the_poses_error():
    """No floor matched (the sparse points were enough): the pairs' residuals alone said 0.0013 deg on a rendered
    network whose floor was 0.008 deg off (benchmarks/README.md); the poses' covariance carried through the sparse
    points' own observations says how far the plane moves with the poses: every frame's pose drawn from the
    covariance, the points triangulated again from their pixels, the plane fitted again and compared with the
    cameras' mean orientation, the tilt lies within 2.45 of the reported sigma in ~95 % of 200 draws; each camera's
    height above that plane (the camera moved with its frame) within 1.96 of its ``pose_camera_height_sigmas``."""
    rec = textured_ground(points=600)
    fit = fit_floor(rec)
    assert fit and fit.points_by_source == {"sparse": fit.num_points, "matched": 0, "markers": 0}
    covariance = per_frame_covariance(rec, np.radians(0.02), 0.005)
    widened = with_pose_uncertainty(FloorEstimate(fit), rec, covariance).fit
    assert np.isfinite(widened.pose_normal_sigma_deg) and widened.pose_normal_sigma_deg > 3 * fit.normal_sigma_deg
    assert widened.normal_sigma_deg == pytest.approx(np.hypot(widened.pose_normal_sigma_deg,
                                                              fit.scatter_normal_sigma_deg))
    assert "poses' covariance" in widened.sigma_basis
    frames = sorted(rec.reg_frame_ids())
    nominal = {f: rec.frame(f).rig_from_world for f in frames}
    tracks = [[(rec.image(e.image_id), rec.image(e.image_id).points2D[e.point2D_idx].xy) for e in p.track.elements]
              for p in rec.points3D.values()]
    rng = np.random.default_rng(3)
    wide = [rec.find_image_with_name(f"rig{k:02d}/wide/frame0000.png") for k in range(1, 9)]
    nominal_heights = np.array([image.projection_center() @ fit.normal + fit.offset for image in wide])
    height_sigmas = np.array([widened.pose_camera_height_sigmas[image.name] for image in wide])
    ratios, height_ratios = [], []
    for _ in range(200):
        moved = {}
        for f in frames:
            w, dt = rng.normal(0, np.radians(0.02), 3), rng.normal(0, 0.005, 3)
            moved[f] = pycolmap.Rigid3d(pycolmap.Rotation3d(w) * nominal[f].rotation, nominal[f].translation + dt)
        points = []
        for track in tracks:  # linear triangulation of each point's exact pixels with the moved poses
            rows = []
            for image, xy in track:
                pose = moved[image.frame_id].matrix()
                ray = (xy - [WIDTH / 2, HEIGHT / 2]) / 450.0
                rows += [ray[0] * pose[2] - pose[0], ray[1] * pose[2] - pose[1]]
            null = np.linalg.svd(np.array(rows))[2][3]
            points.append(null[:3] / null[3])
        normal, offset = fit_plane(np.array(points))
        normal, offset = (normal, offset) if normal @ fit.normal > 0 else (-normal, -offset)
        heights = np.array([moved[image.frame_id].inverse().translation @ normal + offset for image in wide])
        height_ratios.append(np.abs(heights - nominal_heights) / height_sigmas)
        mean = sum(moved[f].rotation.matrix().T @ nominal[f].rotation.matrix() for f in frames)
        u, _, vt = np.linalg.svd(mean)  # the cameras' mean rotation from the nominal world into the moved one
        seen = u @ vt @ fit.normal
        ratios.append(np.degrees(np.arccos(min(abs(normal @ seen), 1.0))) / widened.normal_sigma_deg)
    inside = np.mean(np.array(ratios) <= 2.45)
    assert 0.9 <= inside and np.median(ratios) > 0.5, (inside, np.median(ratios))
    inside = np.mean(np.array(height_ratios) <= 1.96)
    assert 0.9 <= inside and np.median(height_ratios) > 0.4, (inside, np.median(height_ratios))
