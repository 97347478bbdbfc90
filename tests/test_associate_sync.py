"""rigsfm associate tells a rig whose frames are late from the persons (rigsfm.associate.sync), against the truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from test_associate import crowd  # noqa: F401  (the rendered crowd and its run, shared)

from rigsfm.associate import AssociateOptions, associate
from rigsfm.associate.evaluate import true_heads, visible_heads
from rigsfm.associate.output import MANIFEST
from rigsfm.core.errors import InputError

FRAMES = 9
# Geometry only: the recording's later frames have no images beside the run's (the appearance cue would serve the
# first frame alone).
OPTIONS = dict(pixel_sigma=1.5, appearance=False, poses_from="frame0000.png")


def _recording(dataset: Path, offsets: dict[str, int], path: Path, step_m: float = 0.3, seed: int = 0) -> Path:
    """DETECTIONS of a walking crowd over FRAMES frames: the crowd's true heads of frame 0, each walking ``step_m``
    a frame in its own direction, seen by the exact cameras (the heads each view sees in frame 0), 1.5 px noise,
    10 % missed, 5 % false (the issue's detector); rig r's frame k shows the heads at the others' frame k +
    ``offsets[r]``."""
    rng = np.random.default_rng(seed)
    heads = true_heads(dataset, 0)
    heading = rng.uniform(0, 2 * np.pi, len(heads))
    step = step_m * rng.uniform(0.6, 1.4, len(heads))[:, None] * np.c_[np.cos(heading), np.sin(heading),
                                                                         np.zeros(len(heads))]
    exact = {im.name: im for im in pycolmap.Reconstruction(str(dataset / "ground_truth")).images.values()}
    lines = ["image,x,y"]
    for name, (_, ids) in visible_heads(dataset, "frame0000").items():
        image = exact[name]
        width, height = image.camera.width, image.camera.height
        for k in range(FRAMES):
            t = k + offsets.get(name.split("/")[0], 0)
            xy = np.array([image.project_point(p) for p in heads[ids] + t * step[ids]], dtype=np.float64)
            keep = rng.random(len(xy)) >= 0.1
            xy = xy[keep] + rng.normal(0, 1.5, (int(keep.sum()), 2))
            xy = np.r_[xy, rng.uniform([0, 0], [width, height], (rng.binomial(len(ids), 0.05), 2))]
            xy = xy[(xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)]
            frame = name.replace("frame0000", f"frame{k:04d}")
            lines += [f"{frame},{x:.3f},{y:.3f}" for x, y in xy]
    path.write_text("\n".join(lines) + "\n")
    return path


def _offsets(dest: Path) -> dict:
    first = json.loads((dest / "frame0003" / "persons.json").read_text())
    assert json.loads((dest / MANIFEST).read_text())["frame_offsets"] == first["frame_offsets"]
    return first["frame_offsets"]


def test_a_crowd_that_does_not_tell_time_names_no_rig(crowd, tmp_path, caplog):  # noqa: F811
    # four rigs on a 120 degree arc: few persons of three views, so every rig's count is flat in the shift (rig03 +1
    # as well, 5-10 detections a frame): nothing is named, nor told
    dataset, out = crowd
    detections = _recording(dataset, {"rig03": 1}, tmp_path / "heads.csv")
    record = _offsets(associate(out, detections, AssociateOptions(out=tmp_path / "persons", **OPTIONS)))
    assert len(record["tested_frames"]) == 4 and record["named"] == {}, record
    assert all(t["offset"] is None for t in record["rigs"].values()), record
    assert "NOT SYNCHRONISED" not in caplog.text


def test_a_synchronised_recording_names_no_rig(crowd, tmp_path, caplog):  # noqa: F811
    dataset, out = crowd
    detections = _recording(dataset, {}, tmp_path / "heads.csv")
    record = _offsets(associate(out, detections, AssociateOptions(out=tmp_path / "persons", **OPTIONS)))
    assert record["named"] == {} and record["skipped"] is None, record
    assert "NOT SYNCHRONISED" not in caplog.text


def test_a_file_of_offsets_is_applied_and_checked(crowd, tmp_path):  # noqa: F811
    dataset, out = crowd
    detections = _recording(dataset, {"rig02": -1}, tmp_path / "heads.csv")
    offsets = tmp_path / "offsets.yaml"
    offsets.write_text("rig05: 1\n")
    with pytest.raises(InputError, match="rig 'rig05' is not in"):
        associate(out, detections, AssociateOptions(out=tmp_path / "bad", frame_offsets=offsets, **OPTIONS))
    offsets.write_text("rig02: -1\n")
    dest = associate(out, detections, AssociateOptions(out=tmp_path / "file", frame_offsets=offsets, **OPTIONS))
    record = _offsets(dest)
    assert record["applied"] == {"rig02": -1} and record["skipped"], record
    # rig02's frame k was taken at the others' frame k - 1: the others' frame 3 holds its frame 4, its frame 0 none
    assert "rig02/narrow/frame0004.png" in json.loads((dest / "frame0003" / "persons.json").read_text())["views"]
    last = json.loads((dest / f"frame{FRAMES - 1:04d}" / "persons.json").read_text())["views"]
    assert not any(v.startswith("rig02/") for v in last)


def test_frames_are_paired_by_time():
    from rigsfm.associate.detections import from_arrays
    from rigsfm.associate.sync import paired_frames

    names = [f"rig0{r}/narrow/f{k}.png" for r in (1, 2, 3) for k in range(3)]
    detections = from_arrays({n: np.zeros((1, 2)) for n in names})
    assert paired_frames(detections, {"rig03": 1}) == [
        ("f0.png", ["rig01/narrow/f0.png", "rig02/narrow/f0.png"]),
        ("f1.png", ["rig01/narrow/f1.png", "rig02/narrow/f1.png", "rig03/narrow/f0.png"]),
        ("f2.png", ["rig01/narrow/f2.png", "rig02/narrow/f2.png", "rig03/narrow/f1.png"])]


def test_the_warning_names_the_late_rig_and_the_fix():
    from rigsfm.associate.sync import RigTiming, SyncCheck, describe

    check = SyncCheck("check", frames=["f2.png"], search=2, rigs={
        "rig01": RigTiming("rig01/narrow", {-1: 5, 0: 30, 1: 6}, 0, 0.0),
        "rig03": RigTiming("rig03/narrow", {-1: 40, 0: 10, 1: 3}, 1, 4.2)})
    assert check.warning is not None
    assert check.warning.startswith("FRAMES NOT SYNCHRONISED: rig03 is about +1 frame off")
    assert "--frame-offsets auto" in check.warning
    assert describe(check.to_dict()).startswith("frame offsets (check): estimated rig03 +1 frame over 1 frame(s)")
    check.applied = {"rig03": 1}
    assert check.warning is None


def test_a_crowd_that_tells_no_time_is_said_unknown_not_synchronised():
    from rigsfm.associate.sync import SyncCheck, describe, timings

    flat = {f"rig0{k}/narrow": {-1: 20, 0: 21, 1: 19} for k in range(1, 5)}  # no clear peak anywhere
    check = SyncCheck("check", frames=["f2.png"], search=1,
                      rigs={camera.split("/")[0]: t for camera, t in timings(flat).items()})
    assert check.named == {} and check.warning is None
    line = describe(check.to_dict())
    assert "not told" in line and "unknown" in line and "at 0" not in line


def _walking_views(offsets: dict[str, int], frames: int = 7, seed: int = 0) -> list[list]:
    """Per frame, six exact narrow views on a ring 18 m across round 150 heads walking 0.13 m a frame (a tenth of a
    second at 1.3 m/s), the issue's detector (1.5 px, 10 % missed, 5 % false); rig r's frame k shows the heads at
    the others' frame k + ``offsets[r]``."""
    from test_associate_segments import H, W, _view

    rng = np.random.default_rng(seed)
    heads = np.c_[rng.uniform(-3, 3, (150, 2)), rng.uniform(1.6, 1.9, 150)]
    heading = rng.uniform(0, 2 * np.pi, 150)
    step = 0.13 * np.c_[np.cos(heading), np.sin(heading), np.zeros(150)]
    out = []
    for k in range(frames):
        views = []
        for c, angle in enumerate(np.radians(np.arange(0, 360, 60))):
            rig = f"rig0{c + 1}"
            centre = np.array([9 * np.cos(angle), 9 * np.sin(angle), 3.5])
            view = _view(f"{rig}/narrow/frame{k:04d}.png", centre, np.array([0.0, 0.0, 1.7]),
                         heads + (k + offsets.get(rig, 0)) * step)
            inside = (view.xy[:, 0] >= 0) & (view.xy[:, 0] < W) & (view.xy[:, 1] >= 0) & (view.xy[:, 1] < H)
            inside &= rng.random(len(heads)) > 0.1
            xy = view.xy[inside] + rng.normal(0, 1.5, (int(inside.sum()), 2))
            view.xy = np.r_[xy, rng.uniform([0, 0], [W, H], (rng.binomial(int(inside.sum()), 0.05), 2))]
            views.append(view)
        out.append(views)
    return out


def _timed(offsets: dict[str, int]) -> dict:
    """Each rig's offset as rigsfm.associate.sync tells it from frames 2-4 of :func:`_walking_views`, the frames
    associated one after the other as associate_frames does (exact poses: no correction to find)."""
    import copy

    from rigsfm.associate.solve import associate_views
    from rigsfm.associate.sync import shift_counts, timings

    options = AssociateOptions(pixel_sigma=1.5, appearance=False, detection_probability=0.8)
    frames = _walking_views(offsets)
    pristine = copy.deepcopy(frames)
    chain, earlier = [], None
    for views in frames:
        if chain:
            for view, before in zip(views, chain[-1][0]):
                view.carry(before)
        earlier = associate_views(views, options, carried=True, earlier=earlier)
        chain.append((views, earlier))
    cameras = [v.name.rsplit("/", 1)[0] for v in frames[0]]
    windows = [({(c, s): pristine[i + s][v] for v, c in enumerate(cameras) for s in range(-2, 3)},
                dict(zip(cameras, chain[i - 1][0])), chain[i - 1][1]) for i in (2, 3, 4)]
    return {c.split("/")[0]: t.offset for c, t in timings(shift_counts(windows, cameras, 2, options)).items()}


def test_the_walking_crowd_times_a_late_rig_and_names_nobody_when_synchronised():
    assert _timed({"rig03": 1}) == {"rig01": 0, "rig02": 0, "rig03": 1, "rig04": 0, "rig05": 0, "rig06": 0}
    assert _timed({"rig05": -2}) == {"rig01": 0, "rig02": 0, "rig03": 0, "rig04": 0, "rig05": -2, "rig06": 0}
    assert set(_timed({}).values()) == {0}


def test_counts_flat_in_the_shift_name_no_rig():
    from rigsfm.associate.sync import timings

    # a crowd whose persons do not time the views (few of three views): no camera's count peaks, and a chance
    # excess of one shift (rig01's -2, 2.4 sigmas above its count at 0) must not name it
    flat = {"rig01/narrow": {-2: 45, -1: 30, 0: 25, 1: 30, 2: 28}, "rig02/narrow": {-2: 37, -1: 39, 0: 35, 1: 37, 2: 35},
            "rig03/narrow": {-2: 38, -1: 29, 0: 35, 1: 30, 2: 37}, "rig04/narrow": {-2: 24, -1: 24, 0: 30, 1: 38, 2: 30}}
    assert all(t.offset is None for t in timings(flat).values())
    # the same rig among cameras that peak clearly at 0 is named
    clear = {**{f"rig0{r}/narrow": {-2: 10, -1: 20, 0: 90, 1: 22, 2: 9} for r in (2, 3, 4)},
             "rig01/narrow": flat["rig01/narrow"]}
    assert {c: t.offset for c, t in timings(clear).items()} == {
        "rig01/narrow": 2, "rig02/narrow": 0, "rig03/narrow": 0, "rig04/narrow": 0}


def test_auto_pairs_the_frames_of_a_named_rig_by_time(crowd, tmp_path, monkeypatch):  # noqa: F811
    # the 4-rig crowd does not time its views (above), so the check's verdict is given: rig02 -1, as recorded
    from typer.testing import CliRunner

    import rigsfm.associate.sync as sync
    from rigsfm.cli import app

    real = sync.check_frame_offsets

    def named(model, detections, chain, options, asked, applied=None, recording=None):
        check = real(model, detections, chain, options, asked, applied, recording)
        check.rigs["rig02"] = sync.RigTiming("rig02/narrow", {-1: 10, 0: 20, 1: 40}, -1, 3.7)
        return check

    monkeypatch.setattr(sync, "check_frame_offsets", named)
    dataset, out = crowd
    detections = _recording(dataset, {"rig02": -1}, tmp_path / "heads.csv")
    dest = tmp_path / "auto"
    result = CliRunner().invoke(app, ["associate", str(out), str(detections), "--out", str(dest), "--pixel-sigma",
                                      "1.5", "--no-appearance", "--poses-from", "frame0000.png",
                                      "--frame-offsets", "auto"])
    assert result.exit_code == 0, result.output
    assert "frame offsets (auto): estimated rig02 -1 frame" in result.output
    assert "frames paired by time: rig02 -1" in result.output
    record = _offsets(dest)
    assert record["applied"] == {"rig02": -1}, record
    assert "rig02/narrow/frame0004.png" in json.loads((dest / "frame0003" / "persons.json").read_text())["views"]


def test_offsets_count_the_recording_s_frames_in_detections_of_every_second_frame(tmp_path):
    """Detections of every second frame (f0, f2, f4) with rig03 one frame late ('rig03: 1'): its f0 image, taken at
    the others' f1, was paired with their f2, a frame after it was taken (counted in the DETECTIONS' frames, not the
    recording's); on the rendered 8-rig recording 8-12 % of rig03's detections in persons were then the others'
    person (76-81 % with every frame). The recording's frames come from the run's images folder; and the check of
    the rigs' timing, which steps through the DETECTIONS' frames, says it needs consecutive ones."""
    from rigsfm.associate.detections import from_arrays
    from rigsfm.associate.sync import paired_frames, recording_frames, skipped_frames

    names = [f"rig0{r}/narrow/f{k}.png" for r in (1, 2, 3) for k in (0, 2, 4)]
    detections = from_arrays({n: np.zeros((1, 2)) for n in names})
    for r in (1, 2, 3):
        (tmp_path / f"rig0{r}" / "narrow").mkdir(parents=True)
        for k in range(6):
            (tmp_path / f"rig0{r}" / "narrow" / f"f{k}.png").write_bytes(b"")
    (tmp_path / "rig01" / "narrow" / "notes.txt").write_text("not a frame")
    recording = recording_frames(detections, tmp_path, known=["rig01/wide/f0.png"])
    assert recording == [f"f{k}.png" for k in range(6)]
    assert paired_frames(detections, {"rig03": 1}, recording) == [
        ("f0.png", ["rig01/narrow/f0.png", "rig02/narrow/f0.png"]),
        ("f2.png", ["rig01/narrow/f2.png", "rig02/narrow/f2.png"]),
        ("f4.png", ["rig01/narrow/f4.png", "rig02/narrow/f4.png"])]  # rig03's were taken at f1, f3, f5: no one's
    assert paired_frames(detections, {"rig03": 2}, recording) == [
        ("f0.png", ["rig01/narrow/f0.png", "rig02/narrow/f0.png"]),
        ("f2.png", ["rig01/narrow/f2.png", "rig02/narrow/f2.png", "rig03/narrow/f0.png"]),
        ("f4.png", ["rig01/narrow/f4.png", "rig02/narrow/f4.png", "rig03/narrow/f2.png"])]
    assert skipped_frames(detections, recording) == ["f1.png", "f3.png"]
    assert recording_frames(detections) == ["f0.png", "f2.png", "f4.png"]  # no images folder: the DETECTIONS' own
