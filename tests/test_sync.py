"""Unsynchronised recordings (rigsfm.run.checks.sync): narrow images rendered from a floor texture that moves rigidly
between frames (a flat crowd walking), each rig's frame k taken at time k + its offset; the estimate names the
shifted rig and its offset, a synchronised recording is not flagged, and the self-check puts its failures down to
time instead of the calibration."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest
from synthetic_world import HEIGHT, WIDTH, ring
from test_floor_matching import CELL, HALF, render
from test_self_check import fine_texture

from rigsfm.core.errors import InputError
from rigsfm.core.names import name_of
from rigsfm.run.checks.guided import KEYPOINT_NOISE_PX
from rigsfm.run.checks.self_check import epipolar_self_check
from rigsfm.run.checks.sync import (
    CONSISTENT,
    OffsetScore,
    PairSync,
    _solve,
    describe_record,
    estimate_frame_offsets,
    frames_by_time,
    read_frame_offsets,
    search_tolerance,
)
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import SelfCheckOptions, WorldOptions
from rigsfm.run.world.floor_matching import plane_hits
from rigsfm.run.world.frame import place_in_world

FRAMES = 3
STEP_TEXELS = 25  # the texture moves 25 cm along x and y per frame (a walker's 0.35 m)


def cameras_and_rigs(base: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
    """A reconstruction holding ``base``'s cameras and rigs, no frame or image yet."""
    rec = pycolmap.Reconstruction()
    for camera in base.cameras.values():
        rec.add_camera(camera)
    for rig in base.rigs.values():
        rec.add_rig(rig)
    return rec


def recording(base: pycolmap.Reconstruction, frames: int) -> pycolmap.Reconstruction:
    """``base`` (one frame per rig) with ``frames`` frames per rig at the same pose, frameNNNN.png."""
    rec = cameras_and_rigs(base)
    frame_id = image_id = 0
    for frame in base.frames.values():
        images = [base.images[d.id] for d in frame.data_ids]
        for k in range(frames):
            frame_id += 1
            new = pycolmap.Frame(frame_id=frame_id, rig_id=frame.rig_id, rig_from_world=frame.rig_from_world)
            added = []
            for image in images:
                image_id += 1
                parsed = name_of(image)
                added.append(pycolmap.Image(image_id=image_id, name=f"{parsed.rig}/{parsed.sensor}/frame{k:04d}.png",
                                            camera_id=image.camera_id, frame_id=frame_id))
                new.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, image.camera_id),
                                                image_id))
            rec.add_frame(new)
            for image in added:
                rec.add_image(image)
    return rec


def render_at(image: pycolmap.Image, texture: np.ndarray, time_frames: float) -> np.ndarray:
    """``image`` of the floor texture moved ``STEP_TEXELS`` x time along x and y (any real time: the crowd moves
    continuously); at whole times it is ``render`` of the texture rolled by whole texels, but for the wrap."""
    shift = STEP_TEXELS * time_frames
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = image.camera.cam_from_img(np.stack([xs.ravel(), ys.ravel()], axis=1))
    hits, ok = plane_hits(image, np.array([0.0, 0.0, 1.0]), 0.0, 100.0, rays)
    u = (hits[:, 0] + HALF) / CELL - 0.5 - shift
    v = (HALF - hits[:, 1]) / CELL - 0.5 - shift
    ok &= (u >= 0) & (u < texture.shape[1] - 1) & (v >= 0) & (v < texture.shape[0] - 1)
    map_x = np.where(ok, u, -1).reshape(HEIGHT, WIDTH).astype(np.float32)
    map_y = np.where(ok, v, -1).reshape(HEIGHT, WIDTH).astype(np.float32)
    return cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)


@pytest.fixture(scope="module")
def world():
    base = ring(seed=42, num_rigs=5, model_from_truth=pycolmap.Rigid3d(), narrow_model="PINHOLE").reconstruction
    place_in_world(base, None, None, ["rig01"], WorldOptions())
    rec = recording(base, FRAMES)
    return rec, fine_texture(seed=3)


def rendered(world, root, offsets: dict[str, int]):
    import cv2

    rec, texture = world
    for image in rec.images.values():
        parsed = name_of(image)
        if not parsed.is_narrow:
            continue
        t = int(parsed.frame[5:9]) + offsets.get(parsed.rig, 0)
        path = root / image.name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), render(image, np.roll(texture, (STEP_TEXELS * t, STEP_TEXELS * t), axis=(0, 1))))
    poses = narrow_poses(rec, metric=True, world={"frame": "floor"})
    for pair in poses["pairs"]:
        pair["epipolar_band_95_px"] = 1.0
    return poses


def rendered_at(world, root, offsets: dict[str, float], still: bool = False):
    """``rendered`` at any real offsets (``render_at``); ``still``: the texture does not move."""
    import cv2

    rec, texture = world
    for image in rec.images.values():
        parsed = name_of(image)
        if parsed.is_narrow:
            path = root / image.name
            path.parent.mkdir(parents=True, exist_ok=True)
            time = 0.0 if still else int(parsed.frame[5:9]) + offsets.get(parsed.rig, 0.0)
            cv2.imwrite(str(path), render_at(image, texture, time))
    poses = narrow_poses(rec, metric=True, world={"frame": "floor"})
    for pair in poses["pairs"]:
        pair["epipolar_band_95_px"] = 1.0
    return poses


@pytest.mark.parametrize("offsets", [{"rig03": 1}, {"rig02": -2}, {"rig01": -1}, {}],
                         ids=["rig03+1", "rig02-2", "rig01-1", "synchronised"])
def test_the_shifted_rig_and_its_offset_are_named(world, tmp_path, offsets):
    poses = rendered(world, tmp_path, offsets)
    estimate = estimate_frame_offsets(world[0], tmp_path, poses)
    assert estimate.unsynchronised == offsets
    assert estimate.offsets == {f"rig0{k}": offsets.get(f"rig0{k}", 0) for k in range(1, 6)}
    if offsets:
        (rig, off), = offsets.items()
        assert f"FRAMES NOT SYNCHRONISED: {rig} is about {off:+d} frame" in estimate.warning
    else:
        assert estimate.warning is None


def test_self_check_blames_time_and_passes_with_the_offsets_applied(world, tmp_path):
    rec = world[0]
    poses = rendered(world, tmp_path, {"rig03": 1})
    check = epipolar_self_check(rec, tmp_path, poses, SelfCheckOptions(max_frames=FRAMES))
    involved = [p for p in check.pairs if "rig03/" in p.i + p.j and p.verdict in ("ok", "failed")]
    assert involved and all(p.verdict == "failed" for p in involved)
    estimate = estimate_frame_offsets(rec, tmp_path, poses)
    check.blame_time(estimate.unsynchronised, estimate.warning)
    assert not any(p.verdict == "failed" for p in check.pairs)
    assert [w.split(":")[0] for w in check.warnings] == ["FRAMES NOT SYNCHRONISED"]
    applied = epipolar_self_check(rec, tmp_path, poses, SelfCheckOptions(max_frames=FRAMES), {"rig03": 1})
    measured = [p for p in applied.pairs if p.verdict in ("ok", "failed")]
    assert any("rig03/" in p.i + p.j for p in measured) and all(p.verdict == "ok" for p in measured)


def test_the_default_self_check_includes_a_rig_a_frame_later(world, tmp_path):
    """With one frame checked (the default), rig03 at +1 has no frame at the first instant: the check took that
    instant and left rig03's pairs out, saying '... ok, 0 failed' as if every rig were checked."""
    poses = rendered(world, tmp_path, {"rig03": 1})
    check = epipolar_self_check(world[0], tmp_path, poses, SelfCheckOptions(), {"rig03": 1})
    assert check.frames == ["frame0001.png"]
    measured = [p for p in check.pairs if p.verdict in ("ok", "failed")]
    assert any("rig03/" in p.i + p.j for p in measured) and all(p.verdict == "ok" for p in measured)


def test_the_narrow_observations_take_the_frame_a_late_rig_shares(world, tmp_path):
    """The narrow stage's first instant lacked rig03 at +1 (`--frame-offsets FILE`), so rig03 gave no narrow
    observations (a user's run: 180 held-out matches became 90); it takes the self-check's frame now."""
    from rigsfm.run.narrow.observations import find_matches

    rendered(world, tmp_path, {"rig03": 1})
    pairs = find_matches(world[0], tmp_path, SelfCheckOptions(), offsets={"rig03": 1})
    assert {p.frame for p in pairs} == {"frame0001.png"}
    assert any("rig03/" in p.i + p.j and p.matches >= 20 for p in pairs), [(p.i, p.j, p.matches) for p in pairs]


def without(rec: pycolmap.Reconstruction, name: str) -> pycolmap.Reconstruction:
    """``rec`` without the image ``name`` (a narrow image missing from the image folder)."""
    out = cameras_and_rigs(rec)
    drop = rec.find_image_with_name(name).image_id
    for frame in rec.frames.values():
        new = pycolmap.Frame(frame_id=frame.frame_id, rig_id=frame.rig_id, rig_from_world=frame.rig_from_world)
        for data in frame.data_ids:
            if data.id != drop:
                new.add_data_id(data)
        out.add_frame(new)
    for image in rec.images.values():
        if image.image_id != drop:
            out.add_image(pycolmap.Image(image_id=image.image_id, name=image.name, camera_id=image.camera_id,
                                         frame_id=image.frame_id))
    return out


def test_a_missing_narrow_image_does_not_move_the_rigs_later_frames(world, tmp_path):
    """rig02's narrow frame0001 missing: its frame0002 was taken as its second frame, paired with the others'
    frame0001 (and, rendered, rig02 was estimated a frame off where only rig03 is)."""
    rec = without(world[0], "rig02/narrow/frame0001.png")
    grouped = frames_by_time(rec, {"rig03": 1})
    assert "rig02/narrow/frame0002.png" in [im.name for im in grouped["frame0002.png"]]
    assert "rig02/narrow/frame0002.png" not in [im.name for im in grouped["frame0001.png"]]
    poses = rendered(world, tmp_path, {"rig03": 1})
    poses["pairs"] = [p for p in poses["pairs"] if "rig02/narrow/frame0001.png" not in (p["i"], p["j"])]
    estimate = estimate_frame_offsets(rec, tmp_path, poses)
    assert estimate.offsets == {"rig01": 0, "rig02": 0, "rig03": 1, "rig04": 0, "rig05": 0}


def test_frames_are_paired_by_time(world):
    grouped = frames_by_time(world[0], {"rig03": 1})
    first = grouped["frame0001.png"]
    assert "rig03/narrow/frame0000.png" in [im.name for im in first]
    assert "rig01/narrow/frame0001.png" in [im.name for im in first]


def test_solver_keeps_most_rigs_at_zero():
    def pair(a, b, best):
        return PairSync(a, b, [OffsetScore(d, 100, 0.95 if d == best else 0.2) for d in range(-2, 3)])

    # rig03 frame k = the others' frame k + 1: rig01 frame k+1 meets rig03 frame k, so d(rig01, rig03) = -1
    pairs = [pair("rig01", "rig02", 0), pair("rig01", "rig03", -1), pair("rig02", "rig03", -1)]
    assert _solve(["rig01", "rig02", "rig03"], pairs, 2) == {"rig01": 0, "rig02": 0, "rig03": 1}


@pytest.mark.parametrize("band", [0.05, 0.2, 0.5, 1.0, 3.0, 8.0])
def test_a_pairing_that_is_not_simultaneous_scores_low_even_with_a_band_under_a_pixel(band):
    """Matches of walkers that moved spread over the whole search tolerance: their score, the share within band +
    keypoint noise, must stay well under CONSISTENT however narrow the band (with narrow observations a fraction of a
    pixel), else every frame pairing would look simultaneous."""
    assert (band + KEYPOINT_NOISE_PX) / search_tolerance(band) < 0.6 * CONSISTENT


def test_offsets_file_is_checked(tmp_path):
    path = tmp_path / "offsets.yaml"
    path.write_text("rig03: 1\n")
    assert read_frame_offsets(path, ["rig01", "rig03"], {"rig01": 3, "rig03": 3}) == {"rig03": 1}
    for text, message in (("rig09: 1\n", "rig 'rig09' is not in rigs.yaml"),
                          ("rig03: 0.5\n", "whole number of frames"),
                          ("rig03: 3\n", "beyond the recording")):
        path.write_text(text)
        with pytest.raises(InputError, match=message):
            read_frame_offsets(path, ["rig01", "rig03"], {"rig01": 3, "rig03": 3})


def test_an_offsets_file_of_another_form_is_refused_with_the_form_it_takes(tmp_path):
    """An empty file, or the synth's 'rig03=1', or 'rig03:1' (YAML text without the space), said only "expected a
    mapping"; a rig without narrow images said "offsets 1..-1"; 1.0 was refused as not a whole number."""
    path = tmp_path / "offsets.yaml"
    form = r"; write one line per rig that is off, '<rig>: <whole frames>' with a space after the colon"
    for text, message in (("", r"offsets.yaml: the frame offsets file is empty" + form),
                          ("# rig03 is fine\n", r"offsets.yaml: the frame offsets file is empty" + form),
                          ("rig03=1\n", r"found the text 'rig03=1'" + form),
                          ("rig03:1\n", r"found the text 'rig03:1'" + form),
                          ("- rig03: 1\n", r"found a list" + form),
                          ("rig02: 1\n", r"rig 'rig02' has no narrow images, so no offset applies to it; remove the "
                                         r"line$")):
        path.write_text(text)
        with pytest.raises(InputError, match=message):
            read_frame_offsets(path, ["rig01", "rig02", "rig03"], {"rig01": 3, "rig03": 3})
    path.write_text("rig03: 1.0\nrig02: 0\n")
    assert read_frame_offsets(path, ["rig01", "rig02", "rig03"], {"rig01": 3, "rig03": 3}) == {"rig03": 1, "rig02": 0}


@pytest.mark.parametrize("asked", [None, "auto"])
def test_run_names_the_rig_or_applies_the_estimate(world, tmp_path, asked):
    """The run's self-check stage (rigsfm.run.pipeline._self_check), given narrow_poses.json's record: without
    --frame-offsets the failures are put down to time; with --frame-offsets auto the estimate is applied and the
    check passes."""
    from rigsfm.run.options import RunOptions
    from rigsfm.run.pipeline import Inputs, _self_check

    rec = world[0]
    images = tmp_path / "images"
    poses = rendered(world, images, {"rig03": 1})
    options = RunOptions(self_check=SelfCheckOptions(max_frames=FRAMES, frame_offsets=asked))
    check, record = _self_check(poses, Inputs(images, [], [], None), rec, options, None)
    assert record.asked == asked and record.estimate["unsynchronised"] == {"rig03": 1}
    assert not any(p.verdict == "failed" for p in check.pairs)
    if asked is None:
        assert record.applied == {} and [w.split(":")[0] for w in check.warnings] == ["FRAMES NOT SYNCHRONISED"]
        assert any(p.verdict == "not synchronised" for p in check.pairs)
    else:
        assert record.applied == {"rig03": 1} and check.warnings == []
        assert sum(p.verdict == "ok" for p in check.pairs) >= 4


def test_narrow_features_match_only_simultaneous_narrow_images_of_two_rigs():
    from pathlib import Path

    from rigsfm.core.names import Sensor
    from rigsfm.run.inputs.images import ImageEntry
    from rigsfm.run.matching.pairs import image_pairs
    from rigsfm.run.options import MatchingOptions

    images = [ImageEntry(rig, Sensor(sensor), f"f{k}.png", Path(f"{rig}/{sensor}/f{k}.png"))
              for rig in ("rig01", "rig02") for sensor in ("wide", "narrow") for k in range(3)]
    narrow = {"rig01/narrow/f0.png", "rig01/narrow/f1.png", "rig01/narrow/f2.png", "rig02/narrow/f0.png",
              "rig02/narrow/f1.png", "rig02/narrow/f2.png"}

    def narrow_pairs(offsets):
        pairs = image_pairs(images, MatchingOptions(narrow_features=True, frame_offsets=offsets))
        return {p for p in pairs if set(p) <= narrow and p[0].split("/")[0] != p[1].split("/")[0]}

    assert len(narrow_pairs(None)) == 9  # every frame of one rig's narrow camera with every frame of the other's
    assert narrow_pairs({"rig02": 1}) == {("rig01/narrow/f1.png", "rig02/narrow/f0.png"),
                                          ("rig01/narrow/f2.png", "rig02/narrow/f1.png")}
    assert len(image_pairs(images, MatchingOptions(narrow_features=True, frame_offsets={"rig02": 1}))) == \
        len(image_pairs(images, MatchingOptions(narrow_features=True))) - 7


def test_fractions_of_a_frame_are_named_and_estimated(world, tmp_path):
    """Half a frame is consistent at no integer offset; the matches' motion across their lines between a rig's
    consecutive frames measures it: within 0.05 frame (7x the largest error measured on such recordings, a tenth
    of the half frame), and within the reported standard errors (which bound the lines' own error by the band:
    several times the error on these exact views)."""
    offsets = {"rig05": 0.5, "rig02": -0.4}
    poses = rendered_at(world, tmp_path, offsets)
    estimate = estimate_frame_offsets(world[0], tmp_path, poses)
    fractions = estimate.subframe
    for rig, value in fractions.offsets.items():
        assert value == pytest.approx(offsets.get(rig, 0.0), abs=0.05), rig
        assert abs(value - offsets.get(rig, 0.0)) <= fractions.sigmas[rig] < 0.15
    assert set(estimate.named) == {"rig05", "rig02"} and estimate.applicable in ({}, {"rig05": 1})
    assert "rig02 is about -0.4 frame off" in estimate.warning and "rig05 is about +0.5 frame off" in estimate.warning
    assert estimate.to_dict()["subframe"]["named"].keys() == {"rig05", "rig02"}


def test_a_still_crowd_tells_no_fraction(world, tmp_path):
    """Nothing moves: every frame pairing is consistent and no match can tell a fraction (too little motion)."""
    rec, texture = world
    poses = rendered_at((rec, texture), tmp_path, {}, still=True)
    estimate = estimate_frame_offsets(rec, tmp_path, poses)
    assert estimate.named == {} and estimate.warning is None
    assert estimate.offsets == dict.fromkeys(estimate.offsets)  # none told: 'all rigs at 0' was said of a still crowd
    assert all(v is None for v in estimate.subframe.offsets.values())
    assert all("too little motion" in p.reason for p in estimate.subframe.pairs)


def test_run_with_auto_reports_a_fraction_it_cannot_apply(world, tmp_path):
    """--frame-offsets auto on a rig half a frame off: no whole frame to apply, the fraction in the record and the
    warning, and the pairs it spoils put down to time."""
    from rigsfm.run.options import RunOptions
    from rigsfm.run.pipeline import Inputs, _self_check

    images = tmp_path / "images"
    poses = rendered_at(world, images, {"rig05": 0.5})
    options = RunOptions(self_check=SelfCheckOptions(max_frames=FRAMES, frame_offsets="auto"))
    check, record = _self_check(poses, Inputs(images, [], [], None), world[0], options, None)
    assert record.applied in ({}, {"rig05": 1})  # the nearest whole frame of about half a frame
    assert record.estimate["named"]["rig05"] == pytest.approx(0.5, abs=0.05)
    assert not any(p.verdict == "failed" for p in check.pairs)
    assert any(p.verdict == "not synchronised" for p in check.pairs)
    assert check.warnings[0].startswith("FRAMES NOT SYNCHRONISED: rig05 is about +0.5 frame off; whole frames applied")
    line = describe_record(record)  # the terminal's line
    assert "estimated rig05 +0.5 frame (+-0.0" in line and line.endswith("a fraction of a frame is not applied (frames are images)")


def test_fractions_are_combined_with_most_rigs_on_whole_frames():
    """The pairs' fractions measure differences only: the rigs on whole frames of each other (the largest group)
    stay at their integer offsets, whichever rig is first; a rig joined by no measured pair has no offset."""
    from rigsfm.run.checks.subframe import PairFraction, combine

    true = {"rig01": 0.5, "rig02": 0.0, "rig03": 1.0, "rig04": -0.3, "rig05": 0.0}
    integer = {"rig01": 1, "rig02": 0, "rig03": 1, "rig04": 0, "rig05": 0}
    chain = [("rig01", "rig02"), ("rig02", "rig03"), ("rig03", "rig04"), ("rig04", "rig05"), ("rig01", "rig05")]
    pairs = [PairFraction(a, b, integer[a] - integer[b], true[a] - true[b] - integer[a] + integer[b], 0.01, 100, 100)
             for a, b in chain]
    estimate = combine([*true, "rig06"], {**integer, "rig06": 0}, pairs)
    assert {r: round(o, 6) for r, o in estimate.offsets.items() if o is not None} == true
    assert estimate.offsets["rig06"] is None and "no pair" in estimate.reason["rig06"]
    assert estimate.named.keys() == {"rig01", "rig03", "rig04"}
