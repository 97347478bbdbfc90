"""The world stage on synthetic reconstructions with a known floor: the frame it picks, the ground maps it
writes into narrow_poses.json, the refusals of impossible plane heights and the no-floor warning."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
from synthetic_world import ring
from test_bad_input import make_inputs
from typer.testing import CliRunner

from rigsfm.cli import app
from rigsfm.core.errors import InputError
from rigsfm.core.ground import footprints, image_to_plane
from rigsfm.inspect.report.figures import STEREO_SVG
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import WorldFrame, WorldOptions
from rigsfm.run.world.frame import ground_maps, place_in_world, validate_world_options


def names(world):
    return sorted({name.split("/")[0] for name in world.truth_heights})


def test_floor_frame_is_applied_and_described():
    world = ring(seed=20)
    rec = world.reconstruction
    before = {rig_id: {s: t.matrix().copy() for s, t in rig.non_ref_sensors.items()} for rig_id, rig in rec.rigs.items()}
    result = place_in_world(rec, None, None, ["rig02", "rig01"], WorldOptions(plane_heights=(1.7,)))
    assert result.frame == WorldFrame.FLOOR and result.warnings == []
    for name, height in world.truth_heights.items():  # z = height above the floor (5 mm floor noise)
        assert rec.find_image_with_name(name).projection_center()[2] == pytest.approx(height, abs=3e-3)
    rig2 = rec.find_image_with_name("rig02/wide/frame0000.png").projection_center()
    assert rig2[0] > 10 and rig2[1] == pytest.approx(0.0, abs=1e-9)  # x towards the first rig of rigs.yaml
    for rig_id, rig in rec.rigs.items():  # scale 1: E^sl untouched
        for sensor, transform in rig.non_ref_sensors.items():
            np.testing.assert_array_equal(transform.matrix(), before[rig_id][sensor])
    data = result.to_dict()
    assert data["frame"] == "floor" and data["plane_heights_m"] == [0.0, 1.7] and "rig02" in data["x_axis"]
    assert data["floor"]["found"] and data["floor"]["points_by_source"]["sparse"] > 500
    assert data["floor"]["matching"] == {"ran": False, "why": None, "rounds": 0, "image_pairs": 0,
                                         "matched_points": 0, "seconds": 0.0}
    json.dumps(data)


def test_no_floor_keeps_the_mapper_frame_with_a_warning():
    rec = ring(seed=21, floor_points=0, wall_points=0, box_points=0, pillar_points=5).reconstruction
    pose = rec.images[1].cam_from_world().matrix().copy()
    result = place_in_world(rec, None, None, ["rig01"], WorldOptions(plane_heights=(1.7,)))
    assert result.frame == WorldFrame.MAPPING and result.plane_heights == ()
    (warning,) = result.warnings
    assert warning.startswith("NO FLOOR FOUND: ") and "give known-length markers on the floor" in warning
    assert "--world mapping" in warning
    np.testing.assert_array_equal(rec.images[1].cam_from_world().matrix(), pose)
    assert result.to_dict()["floor"]["found"] is False


def test_mapping_frame_is_kept_when_asked():
    rec = ring(seed=22).reconstruction
    pose = rec.images[1].cam_from_world().matrix().copy()
    result = place_in_world(rec, None, None, ["rig01"], WorldOptions(frame=WorldFrame.MAPPING))
    assert result.frame == WorldFrame.MAPPING and result.estimate is None and not result.warnings
    np.testing.assert_array_equal(rec.images[1].cam_from_world().matrix(), pose)


@pytest.mark.parametrize("height,words", [(-0.5, "below the floor"), (float("nan"), "nan is not a height")])
def test_negative_plane_height_is_refused(height, words):
    with pytest.raises(InputError, match=words):
        validate_world_options(WorldOptions(plane_heights=(height,)))


def test_plane_height_needs_the_floor_frame():
    with pytest.raises(InputError, match="leave out --world mapping"):
        validate_world_options(WorldOptions(frame=WorldFrame.MAPPING, plane_heights=(1.7,)))


def test_plane_above_the_cameras_is_refused_before_the_model_moves():
    rec = ring(seed=23).reconstruction  # cameras 3.25-3.75 m up; narrow 6 cm lower at most
    pose = rec.images[1].cam_from_world().matrix().copy()
    with pytest.raises(InputError, match=r"--plane-height 3.9 m is above the narrow cameras \(the lowest, rig"):
        place_in_world(rec, None, None, ["rig01"], WorldOptions(plane_heights=(3.9,)))
    np.testing.assert_array_equal(rec.images[1].cam_from_world().matrix(), pose)


def test_cli_refuses_a_negative_plane_height_in_one_line(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", str(images), "--rigs", str(rigs_path), "--out", str(out),
                                      "--plane-height", "-1"])
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--plane-height -1 m is below the floor" in lines[0], result.output
    assert not out.exists()


def test_ground_maps_in_narrow_poses_map_pixels_to_metres():
    world = ring(seed=24, num_rigs=6)
    rec = world.reconstruction
    result = place_in_world(rec, None, None, names(world), WorldOptions(plane_heights=(1.7,)))
    maps = ground_maps(rec, result.plane_heights)
    data = json.loads(json.dumps(narrow_poses(rec, metric=True, world=result.to_dict(),
                                              ground=maps)))
    assert data["world"]["frame"] == "floor" and data["ground"]["plane_heights_m"] == [0.0, 1.7]
    assert {"ground_from_image", "footprint_m", "gsd_mm_per_px", "ground_overlap_m2"} <= set(data["conventions"])
    rng = np.random.default_rng(0)
    for entry in data["narrow"]:
        image = rec.find_image_with_name(entry["name"])
        camera = image.camera
        for k, plane in enumerate(entry["ground"]):
            assert plane["plane_height_m"] == [0.0, 1.7][k]
            raw = np.c_[rng.uniform(0, camera.width, 50), rng.uniform(0, camera.height, 50)]
            expected, ok = image_to_plane(image, raw, plane["plane_height_m"])
            undistorted = np.asarray(camera.cam_from_img(raw[ok])) @ np.asarray(camera.calibration_matrix())[:2, :2].T
            undistorted += np.asarray(camera.calibration_matrix())[:2, 2]
            xyw = np.c_[undistorted, np.ones(len(undistorted))] @ np.asarray(plane["ground_from_image"]).T
            assert (xyw[:, 2] > 0).all()
            np.testing.assert_allclose(xyw[:, :2] / xyw[:, 2:], expected[ok], atol=1e-6)
            assert plane["footprint_area_m2"] > 1 and plane["gsd_mm_per_px"] > 0
    overlaps = [p["ground_overlap_m2"] for p in data["pairs"]]
    assert all(len(o) == 2 for o in overlaps) and max(o[0] for o in overlaps) > 1.0
    prints = footprints(rec, "narrow", 0.0)
    assert data["ground"]["seen_by_two_or_more_m2"][0] <= sum(fp.area for fp in prints.values())


def test_two_frames_of_one_camera_are_not_two_cameras():
    """Coverage and overlaps count cameras: a second frame of a static rig adds no 'seen twice' area."""
    world = ring(seed=25, num_rigs=4)
    rec = world.reconstruction
    single = ground_maps(rec, (0.0,)).seen_twice_m2[0]
    assert single > 1.0
    image = rec.find_image_with_name("rig01/narrow/frame0000.png")
    frame = pycolmap.Frame(frame_id=99, rig_id=rec.frame(image.frame_id).rig_id,
                           rig_from_world=rec.frame(image.frame_id).rig_from_world)
    copy = pycolmap.Image(image_id=99, name="rig01/narrow/frame0001.png", camera_id=image.camera_id, frame_id=99)
    frame.add_data_id(copy.data_id)
    rec.add_frame(frame)
    rec.add_image(copy)
    maps = ground_maps(rec, (0.0,))
    assert maps.seen_twice_m2[0] == pytest.approx(single)
    assert maps.overlap("rig01/narrow/frame0000.png", "rig01/narrow/frame0001.png") is None
    assert len(maps.per_image) == 5  # four cameras, one of them twice


def test_report_shows_the_floor_map_and_the_self_check(tmp_path):
    from test_camera_files import finished_workspace

    from rigsfm.core.io import write_json_atomic
    from rigsfm.core.summary import Summary
    from rigsfm.inspect.report.write import write_report

    finished_workspace(tmp_path / "out")
    narrow = json.loads((tmp_path / "out" / "narrow_poses.json").read_text())
    pair = {"frame": "f0.png", "i": "rig01/narrow/f0.png", "j": "rig02/narrow/f0.png", "band_px": 1.2,
            "matches": 300, "median_px": 2.0, "p95_px": 4.5, "within_band": 0.2, "band_matches": 40,
            "measured_within_px": 14.0, "verdict": "failed"}
    summary = Summary.from_json({
        "world": narrow["world"], "warnings": ["EPIPOLAR CHECK FAILED: 1 of 1 narrow pairs ..."],
        "epipolar_self_check": {"frames": ["f0.png"], "guided_by": "epipolar band", "skipped": None, "seconds": 1.0,
                                "settings": {"wide_factor": 5.0}, "pairs": [pair]}})
    write_json_atomic(tmp_path / "out" / "summary.json", summary.to_json())
    page = write_report(tmp_path / "out").read_text()
    world = page[page.index("<h2>World frame and floor map</h2>"):page.index("<h2>Narrow camera pairs</h2>")]
    assert "sparse 6" in world and "towards the first registered rig of rigs.yaml (rig01)" in world
    svg = world[world.index("<svg"):world.index("</svg>")]
    assert svg.count("<title>rig0") == 4  # one footprint per narrow camera
    assert f'fill="{STEREO_SVG}"' in svg  # the areas seen by two or more narrow cameras
    assert "seen by two or more narrow cameras: " in world.replace("Area seen", "seen")
    check = page[page.index("<h2>Epipolar self-check"):]
    assert '<span class="warn">failed</span>' in check and "14" in check and "4.5" in check



def test_the_mapper_frame_is_described_as_metric_only_on_a_metric_result():
    """summary.json's world of a run without scale said 'after the metric adjustment'."""
    from rigsfm.run.options import WorldFrame
    from rigsfm.run.world.frame import WorldResult

    metric = WorldResult(WorldFrame.MAPPING, WorldFrame.MAPPING, metric=True).summary().description
    arbitrary = WorldResult(WorldFrame.FLOOR, WorldFrame.MAPPING, metric=False).summary().description
    assert "metric adjustment" in metric
    assert arbitrary == "the mapper's frame (arbitrary orientation, origin and units)"
