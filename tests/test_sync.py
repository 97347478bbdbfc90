"""Unsynchronised recordings (rigsfm.run.checks.sync): narrow images rendered from a floor texture that moves rigidly
between frames (a flat crowd walking), each rig's frame k taken at time k + its offset; the estimate names the
shifted rig and its offset, a synchronised recording is not flagged, and the self-check puts its failures down to
time instead of the calibration."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from synthetic_world import ring
from test_floor_matching import render
from test_self_check import fine_texture

from rigsfm.core.errors import InputError
from rigsfm.core.names import name_of
from rigsfm.run.checks.self_check import epipolar_self_check
from rigsfm.run.checks.sync import (
    OffsetScore,
    PairSync,
    _solve,
    estimate_frame_offsets,
    frames_by_time,
    read_frame_offsets,
)
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import SelfCheckOptions, WorldOptions
from rigsfm.run.world.frame import place_in_world

FRAMES = 3
STEP_TEXELS = 25  # the texture moves 25 cm along x and y per frame (a walker's 0.35 m)


def recording(base: pycolmap.Reconstruction, frames: int) -> pycolmap.Reconstruction:
    """``base`` (one frame per rig) with ``frames`` frames per rig at the same pose, frameNNNN.png."""
    rec = pycolmap.Reconstruction()
    for camera in base.cameras.values():
        rec.add_camera(camera)
    for rig in base.rigs.values():
        rec.add_rig(rig)
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
