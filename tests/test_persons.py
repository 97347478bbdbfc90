"""3D persons in the synthetic arena (rigsfm.synth.persons): exact ray casting, head truth, walking, unsynchronised
rigs, and the scene without persons left as it was."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest
import yaml

from rigsfm.core.errors import InputError
from rigsfm.core.geometry import project_world
from rigsfm.synth import SceneOptions, build_arena, make_rigs, render_clean, render_dataset, render_image
from rigsfm.synth.__main__ import main
from rigsfm.synth.dataset import heads_in_image
from rigsfm.synth.persons import (
    HEAD,
    HEAD_RADIUS,
    HEIGHT_RANGE,
    Persons,
    _pair_hits,
    build_crowd,
    intersect,
    parse_frame_offsets,
    read_person_truth,
)
from rigsfm.synth.render import LIGHT, pixel_rays
from rigsfm.synth.scene import PERSON, trace

# A small crowd seen large enough to check pixels: narrow heads ~25 px across at image scale 0.25.
CROWD = SceneOptions(num_rigs=2, image_scale=0.25, persons_per_m2=1.0, calibration_noise=False, seed=3)


@pytest.fixture(scope="module")
def crowd_dataset(rendered):
    return rendered(CROWD)


def _crowd(options: SceneOptions, times=(0.0,)):
    crowd = build_crowd(options, list(times))
    assert crowd is not None
    return crowd


def test_culled_ray_casting_equals_testing_every_person(monkeypatch):
    """intersect's (azimuth, elevation) grid and nearest-first pruning return the very hits that testing every ray
    against every person gives: a camera's rays stopped by the static scene, rays in every direction from amid the
    crowd (persons across the grid's +-pi seam whichever way it falls), and from an eye inside a person."""
    from rigsfm.synth import persons as module

    monkeypatch.setattr(module, "PAIRS_PER_CHUNK", 3000)  # many chunks: the pruning between them is exercised
    options = SceneOptions(persons_per_m2=2.0, seed=1, image_scale=0.1)
    persons = _crowd(options).at(0.0)
    rng = np.random.default_rng(0)
    rig = make_rigs(options)[2]
    world_from_cam = rig.narrow_from_world.inverse().matrix()
    camera_rays = pixel_rays(rig.narrow) @ world_from_cam[:, :3].T
    static = trace(build_arena(options), world_from_cam[:, 3], camera_rays).t
    everywhere = rng.normal(size=(20000, 3))
    everywhere[:, 2] = -np.abs(everywhere[:, 2]) * 0.3
    everywhere /= np.linalg.norm(everywhere, axis=1, keepdims=True)
    grid = np.stack(np.meshgrid(np.linspace(-3, 3, 61), np.linspace(-3, 3, 61)), axis=-1).reshape(-1, 2)
    gap = np.min(np.linalg.norm(grid[:, None] - persons.xy[None], axis=2), axis=1)
    amid = grid[np.argmax(gap)]
    assert gap.max() > 0.3
    cases = [(world_from_cam[:, 3], camera_rays, static), (np.array([*amid, 2.5]), everywhere, None),
             (np.array([*(persons.xy[7] + [0.05, 0.0]), 1.0]), everywhere, None)]
    for origin, dirs, bound in cases:
        found = intersect(persons, origin, dirs, bound)
        best = np.full(len(dirs), np.inf) if bound is None else bound.copy()
        who = np.full(len(dirs), -1)
        for p in range(len(persons)):  # every person, every ray
            t, _ = _pair_hits(persons, origin, dirs, np.arange(len(dirs)), np.full(len(dirs), p))
            closer = t < best
            best[closer], who[closer] = t[closer], p
        expected = np.flatnonzero(who >= 0)
        assert len(expected) > 200
        np.testing.assert_array_equal(found.rows, expected)
        np.testing.assert_array_equal(found.person, who[expected])
        np.testing.assert_array_equal(found.t, best[expected])


def test_persons_keep_heights_separation_and_the_disc_while_walking():
    options = SceneOptions(persons_per_m2=4.0, seed=2, frame_period_s=0.5)
    crowd = _crowd(options, [-2.0, 6.0])
    assert np.all((crowd.height >= HEIGHT_RANGE[0]) & (crowd.height <= HEIGHT_RANGE[1]))
    assert abs(len(crowd) / (np.pi * (options.centre_radius - 0.5) ** 2) - 4.0) < 0.01
    from scipy.spatial import cKDTree

    for xy in crowd.xy:  # every simulated step, before and after time 0
        assert not cKDTree(xy).query_pairs(options.person_separation * (1 - 1e-6))
        assert np.hypot(xy[:, 0], xy[:, 1]).max() <= options.centre_radius - 0.5 + 1e-9
    heads = [crowd.at(t).head_centres() for t in (-2.0, 0.0, 1.0, 6.0)]
    for h in heads:
        np.testing.assert_allclose(h[:, 2] + HEAD_RADIUS, crowd.height, rtol=0, atol=1e-12)
    speed = np.linalg.norm(heads[2][:, :2] - heads[1][:, :2], axis=1) / options.frame_period_s
    assert 0.3 < np.median(speed) < 1.3 and speed.max() < 2.0, np.percentile(speed, [5, 50, 95])
    # Time 0 does not depend on the span simulated, so datasets with other frames or offsets agree.
    np.testing.assert_array_equal(_crowd(options).at(0.0).xy, crowd.at(0.0).xy)
    np.testing.assert_array_equal(_crowd(options, [0.0, 3.0]).at(1.0).xy, crowd.at(1.0).xy)


def test_visible_heads_are_where_their_pixels_are(crowd_dataset):
    """For every fully visible head of the narrow images, the head's pixels (from the renderer's own hits) have
    their centroid within 0.15 px of the truth's projection (COLMAP pixels), and the image there has the head's
    grey, shaded as the renderer shades it."""
    truth = read_person_truth(crowd_dataset.root)
    persons = _crowd(CROWD).at(0.0)
    arena = build_arena(CROWD).with_persons(persons)
    gt = crowd_dataset.load_ground_truth()
    checked = 0
    for image in gt.images.values():
        if "/narrow/" not in image.name:
            continue
        camera, pose = gt.cameras[image.camera_id], image.cam_from_world()
        heads = truth.images[image.name]
        np.testing.assert_allclose(heads.xy, project_world(camera, pose, truth.heads[(image.name[:5], 0)][
            heads.person])[0], rtol=0, atol=1e-3)
        world_from_cam = pose.inverse().matrix()
        hits = trace(arena, world_from_cam[:, 3], pixel_rays(camera) @ world_from_cam[:, :3].T)
        label = np.where((hits.kind == PERSON) & (hits.u == HEAD), hits.object_index, -1)
        label = label.reshape(camera.height, camera.width)
        pixels = cv2.imread(str(crowd_dataset.images / image.name), cv2.IMREAD_UNCHANGED).astype(float)
        y, x = np.mgrid[: camera.height, : camera.width] + 0.5
        eye = world_from_cam[:, 3]
        for p, xy, fraction in zip(heads.person, heads.xy, heads.visible_fraction, strict=True):
            if fraction < 1 or not (20 < xy[0] < camera.width - 20 and 20 < xy[1] < camera.height - 20):
                continue
            mine = label == p
            assert mine.sum() > 100
            np.testing.assert_allclose([x[mine].mean(), y[mine].mean()], xy, rtol=0, atol=0.15)
            normal = eye - persons.head_centres()[p]
            normal /= np.linalg.norm(normal)
            r2 = ((xy[0] - camera.principal_point_x) ** 2 + (xy[1] - camera.principal_point_y) ** 2) / (
                (camera.width / 2) ** 2 + (camera.height / 2) ** 2)
            expected = 255 * persons.greys[p, HEAD] * (0.62 + 0.38 * max(normal @ LIGHT, 0)) * (
                1 - CROWD.vignetting * r2)
            observed = pixels[int(xy[1]) - 1: int(xy[1]) + 1, int(xy[0]) - 1: int(xy[0]) + 1].mean()
            assert abs(observed - expected) < 3.0, (image.name, p, observed, expected)
            checked += 1
    assert checked >= 10


def test_a_head_behind_another_is_invisible():
    """A second person put on the ray to a visible head, nearer the camera, hides it: visible false, fraction 0;
    the nearer head is visible. Every invisible head of the crowd (wide view) has something else first on its
    centre's ray."""
    options = CROWD
    rig = make_rigs(options)[0]
    persons = _crowd(options).at(0.0)
    arena = build_arena(options)
    camera, pose = rig.narrow, rig.narrow_from_world
    heads = heads_in_image(arena.with_persons(persons), camera, pose)
    target = int(heads.person[np.flatnonzero(heads.visible_fraction == 1)[0]])
    eye = rig.centre("narrow")
    head = persons.head_centres()[target]
    ray = (head - eye) / np.linalg.norm(head - eye)
    blocker = head - ray * (1.0 / np.hypot(*ray[:2]))  # 1 m nearer, horizontally
    one = Persons(np.vstack([persons.xy[target], blocker[:2]]), np.zeros(2),
                  np.array([persons.height[target], blocker[2] + HEAD_RADIUS]), persons.greys[[target, target]])
    alone = heads_in_image(arena.with_persons(Persons(one.xy[:1], one.yaw[:1], one.height[:1], one.greys[:1])),
                           camera, pose)
    assert alone.visible.tolist() == [True] and alone.visible_fraction.tolist() == [1.0]
    both = heads_in_image(arena.with_persons(one), camera, pose)
    assert both.person.tolist() == [0, 1]
    assert both.visible.tolist() == [False, True]
    assert both.visible_fraction.tolist() == [0.0, 1.0]

    crowd_heads = heads_in_image(arena.with_persons(persons), rig.wide, rig.wide_from_world)
    hidden = crowd_heads.person[~crowd_heads.visible]
    assert len(hidden) > 5
    eye = rig.centre("wide")
    centres = persons.head_centres()[hidden]
    dirs = (centres - eye) / np.linalg.norm(centres - eye, axis=1, keepdims=True)
    hits = trace(arena.with_persons(persons), eye, dirs)
    assert np.all((hits.kind != PERSON) | (hits.object_index != hidden) | (hits.u != HEAD))
    assert np.all(hits.t < np.linalg.norm(centres - eye, axis=1) - HEAD_RADIUS + 1e-9)


def test_frame_offsets_shift_the_persons_by_exactly_those_frames(tmp_path):
    """rig02 with offset 1 sees at its frame k the crowd rig02 of a synchronised dataset sees at frame k + 1 (same
    heads, same visibility, same pixels); offset 0.5 sees the crowd half a frame later."""
    base = SceneOptions(num_rigs=2, image_scale=0.1, persons_per_m2=2.0, frames_per_rig=2, seed=4)
    from dataclasses import replace

    synced = read_person_truth(render_dataset(tmp_path / "synced", replace(base, frames_per_rig=3)).root)
    shifted = render_dataset(tmp_path / "shifted", replace(base, frame_offsets=(("rig02", 1.0),)))
    truth = read_person_truth(shifted.root)
    assert truth.offsets == {"rig01": 0.0, "rig02": 1.0}
    for frame in (0, 1):
        np.testing.assert_array_equal(truth.heads[("rig02", frame)], synced.heads[("rig02", frame + 1)])
        np.testing.assert_array_equal(truth.heads[("rig01", frame)], synced.heads[("rig01", frame)])
        assert truth.time_s[("rig02", frame)] == (frame + 1) * base.frame_period_s
        for sensor in ("wide", "narrow"):
            mine = truth.images[f"rig02/{sensor}/frame{frame:04d}.png"]
            theirs = synced.images[f"rig02/{sensor}/frame{frame + 1:04d}.png"]
            np.testing.assert_array_equal(mine.person, theirs.person)
            np.testing.assert_array_equal(mine.xy, theirs.xy)
            np.testing.assert_array_equal(mine.visible, theirs.visible)
    assert not np.array_equal(synced.heads[("rig02", 0)], synced.heads[("rig02", 1)])  # they do walk
    half = read_person_truth(render_dataset(tmp_path / "half", replace(base, frame_offsets=(("rig02", 0.5),))).root)
    between = _crowd(base, [1.5]).at(0.5).head_centres()  # interpolated between two simulation steps
    np.testing.assert_allclose(half.heads[("rig02", 0)], between, rtol=0, atol=1e-6)
    walked = [np.linalg.norm(between - synced.heads[("rig02", k)], axis=1) for k in (0, 1)]
    assert 0.1 < np.median(walked[0]) < 0.5 and 0.1 < np.median(walked[1]) < 0.5
    observed = cv2.imread(str(shifted.images / "rig02/narrow/frame0000.png"), cv2.IMREAD_UNCHANGED) / 255.0
    rig, arena = make_rigs(base)[1], build_arena(base)
    crowd = _crowd(base, [1.0])
    error = {t: np.abs(observed - render_clean(arena.with_persons(crowd.at(t)), rig.narrow, rig.narrow_from_world)
                       ).mean() for t in (0.0, 1.0)}
    assert error[1.0] < 0.01 < error[0.0], error


def test_persons_change_only_the_pixels_they_cover_and_the_default_scene_is_pinned():
    """Without persons the images are those rendered before persons existed (pinned SHA-256 of a tiny scene); with
    persons, every pixel whose ray meets no person is bit-identical to the render without them."""
    options = SceneOptions(num_rigs=2, image_scale=0.1)
    rig = make_rigs(options)[1]
    arena = build_arena(options)
    digests = [hashlib.sha256(render_image(arena, camera, pose, np.random.default_rng(5)).tobytes()).hexdigest()
               for camera, pose in ((rig.wide, rig.wide_from_world), (rig.narrow, rig.narrow_from_world))]
    assert digests == ["7c62def26c362a4a1c7e3b6a32a70a49de7a8094ba4cfced6f7a8905b1cd3902",
                       "8263861432be7c0e2486fcfd14d98bfc2d791863da19732931fca9d5bfef5b2d"]
    crowded = arena.with_persons(_crowd(SceneOptions(num_rigs=2, image_scale=0.1, persons_per_m2=3.0)).at(0.0))
    for camera, pose in ((rig.wide, rig.wide_from_world), (rig.narrow, rig.narrow_from_world)):
        world_from_cam = pose.inverse().matrix()
        kind = trace(crowded, world_from_cam[:, 3], pixel_rays(camera) @ world_from_cam[:, :3].T).kind
        person = (kind == PERSON).reshape(camera.height, camera.width)
        assert 0.05 < person.mean() < 0.99
        with_persons, without = render_clean(crowded, camera, pose), render_clean(arena, camera, pose)
        np.testing.assert_array_equal(with_persons[~person], without[~person])
        assert np.abs(with_persons[person] - without[person]).mean() > 0.05


def test_jpeg_and_exposure_jitter(tmp_path):
    from dataclasses import replace

    plain = SceneOptions(num_rigs=2, image_scale=0.1, calibration_noise=False, noise_sigma=0.0)
    jittered = replace(plain, exposure_jitter=0.15, jpeg_quality=90)
    render_dataset(tmp_path / "plain", plain)
    data = render_dataset(tmp_path / "jpeg", jittered)
    assert all(name.endswith(".jpg") for name in data.image_names) and len(data.image_names) == 4
    assert sorted(im.name for im in data.load_ground_truth().images.values()) == sorted(data.image_names)
    gains = yaml.safe_load((data.root / "scene.yaml").read_text())["exposure_gain"]
    assert sorted(gains) == sorted(data.image_names) and len(set(gains.values())) == 4
    assert all(0.85 <= g <= 1.15 for g in gains.values())
    for name in data.image_names:
        jpeg = cv2.imread(str(data.images / name), cv2.IMREAD_UNCHANGED).astype(float)
        png = cv2.imread(str(tmp_path / "plain" / "images" / name.replace(".jpg", ".png")),
                         cv2.IMREAD_UNCHANGED).astype(float)
        assert jpeg.shape == png.shape
        unclipped = (png > 10) & (png < 200)
        assert abs(jpeg[unclipped].sum() / png[unclipped].sum() - gains[name]) < 0.01, name


def test_bad_person_options_say_what_to_fix(capsys, tmp_path):
    assert parse_frame_offsets("rig02=1, rig05=-2.5,") == (("rig02", 1.0), ("rig05", -2.5))
    for text in ("rig02", "rig02=x", "=1", "rig02=1,rig02=2"):
        with pytest.raises(ValueError, match="frame offset"):
            parse_frame_offsets(text)
    with pytest.raises(ValueError, match="unknown rigs rig09"):
        SceneOptions(num_rigs=8, frame_offsets=(("rig09", 1.0),))
    with pytest.raises(ValueError, match="too dense"):
        build_crowd(SceneOptions(persons_per_m2=7.0))
    assert main([str(tmp_path / "out"), "--frame-offsets", "rig2:1"]) == 2
    assert main([str(tmp_path / "out"), "--jpeg-quality", "101"]) == 2
    with pytest.raises(InputError, match="no heads.csv"):
        read_person_truth(tmp_path)
