"""EasyMocap intri/extri.yml and aniposelib calibration.toml, read back with the real readers.

The projection of a world point through the file (cv2.projectPoints / aniposelib's camera.project, both with
the file's K, distortion, rvec, tvec) must equal pycolmap's ``img_from_cam`` minus 0.5 px to 1e-6 px.
EasyMocap itself is not installed; ``read_easymocap`` transcribes the key accesses of its ``read_camera``
(easymocap/mytools/camera_utils.py): FileStorage, ``names`` as a string list, ``K_``, ``dist_``, ``H_``/``W_``
via ``int(node.real())``, ``R_`` through ``cv2.Rodrigues``, ``T_``.
"""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest
import tomllib
from aniposelib.cameras import CameraGroup

from rigsfm.core.errors import InputError
from rigsfm.inspect.camera_files import opencv_intrinsics, write_opencv, write_toml

MODELS = {
    "SIMPLE_PINHOLE": [900.0, 401.3, 305.2],
    "PINHOLE": [1801.5, 1799.2, 409.9, 309.9],
    "SIMPLE_RADIAL": [450.2, 403.0, 309.1, -0.09],
    "RADIAL": [451.0, 404.2, 308.7, -0.1, 0.02],
    "OPENCV": [450.5, 449.4, 402.9, 309.1, -0.0987, 0.0006, 0.0002, -0.0003],
    "FULL_OPENCV": [450.5, 449.4, 402.9, 309.1, -0.12, 0.03, 0.0004, -0.0002, 0.001, 0.01, -0.002, 0.0005],
    "OPENCV_FISHEYE": [300.0, 301.0, 406.0, 308.0, 0.05, -0.01, 0.002, -0.0004],
    "SIMPLE_RADIAL_FISHEYE": [300.0, 406.0, 308.0, 0.04],
    "RADIAL_FISHEYE": [300.0, 406.0, 308.0, 0.04, -0.008],
}
FISHEYE = {"OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}


def random_pose(rng: np.random.Generator) -> pycolmap.Rigid3d:
    q = rng.normal(size=4)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(q / np.linalg.norm(q)), rng.uniform(-20, 20, 3))


def make_reconstruction(models: dict[str, list[float]], seed: int = 0, rig_names=None) -> pycolmap.Reconstruction:
    """One camera per model, each with a trivial rig and one posed image ``<rig>/<sensor>/f0.png``."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    for camera_id, (model, params) in enumerate(models.items(), start=1):
        camera = pycolmap.Camera.create_from_model_name(camera_id, model, 1.0, 812, 617)
        camera.params = params
        rec.add_camera_with_trivial_rig(camera)
        rig = rig_names[camera_id - 1] if rig_names else f"rig{camera_id:02d}"
        image = pycolmap.Image(image_id=camera_id, name=f"{rig}/wide/f0.png", camera_id=camera_id)
        rec.add_image_with_trivial_frame(image, random_pose(rng))
    return rec


def points_in_view(image: pycolmap.Image, rng: np.random.Generator, n: int = 50) -> np.ndarray:
    """World points that project inside the image (COLMAP pixels away from the border), 2-40 units deep."""
    camera = image.camera
    pixels = np.c_[rng.uniform(20, camera.width - 20, n), rng.uniform(20, camera.height - 20, n)]
    rays = np.c_[camera.cam_from_img(pixels), np.ones(n)]
    in_cam = rays * rng.uniform(2, 40, n)[:, None]
    return np.array([image.cam_from_world().inverse() * p for p in in_cam])


def expected_opencv_pixels(image: pycolmap.Image, world: np.ndarray) -> np.ndarray:
    in_cam = np.array([image.cam_from_world() * p for p in world])
    return image.camera.img_from_cam(in_cam) - 0.5


def read_easymocap(intri_path, extri_path) -> dict:
    intri = cv2.FileStorage(str(intri_path), cv2.FILE_STORAGE_READ)
    extri = cv2.FileStorage(str(extri_path), cv2.FILE_STORAGE_READ)
    node = intri.getNode("names")
    names = []
    for i in range(node.size()):
        value = node.at(i).string()
        names.append(value if value != "" else str(int(node.at(i).real())))
    cameras = {}
    for name in names:
        rvec = extri.getNode(f"R_{name}").mat()
        cameras[name] = {
            "K": intri.getNode(f"K_{name}").mat(),
            "dist": intri.getNode(f"dist_{name}").mat(),
            "H": int(intri.getNode(f"H_{name}").real()),
            "W": int(intri.getNode(f"W_{name}").real()),
            "Rvec": rvec,
            "R": cv2.Rodrigues(rvec)[0],
            "Rot": extri.getNode(f"Rot_{name}").mat(),
            "T": extri.getNode(f"T_{name}").mat(),
        }
    ext_names = extri.getNode("names")
    assert [ext_names.at(i).string() for i in range(ext_names.size())] == names
    return cameras


def test_easymocap_yaml_projects_like_pycolmap(tmp_path):
    pinhole_models = {m: p for m, p in MODELS.items() if m not in FISHEYE}
    rec = make_reconstruction(pinhole_models)
    paths = write_opencv(rec, tmp_path)
    assert [p.name for p in paths] == ["intri.yml", "extri.yml"]
    assert paths[0].read_text().startswith("%YAML:1.0\n")
    cameras = read_easymocap(*paths)
    rng = np.random.default_rng(1)
    assert sorted(cameras) == [f"rig{i:02d}_wide" for i in range(1, len(pinhole_models) + 1)]
    for image in rec.images.values():
        cam = cameras[image.name.split("/")[0] + "_wide"]
        assert (cam["W"], cam["H"]) == (812, 617)
        assert cam["dist"].shape == ((1, 8) if image.camera.model.name == "FULL_OPENCV" else (1, 5))
        np.testing.assert_allclose(cam["Rot"], cam["R"], atol=1e-12)
        world = points_in_view(image, rng)
        projected, _ = cv2.projectPoints(world, cam["Rvec"], cam["T"], cam["K"], cam["dist"])
        np.testing.assert_allclose(projected.reshape(-1, 2), expected_opencv_pixels(image, world), atol=1e-6, rtol=0)


def test_aniposelib_toml_projects_like_pycolmap(tmp_path):
    rec = make_reconstruction(MODELS)
    (path,) = write_toml(rec, tmp_path, metadata={"world": "test"})
    group = CameraGroup.load(str(path))
    assert tomllib.loads(path.read_text())["metadata"]["world"] == "test"
    assert group.metadata["source"] == "rigsfm"
    by_name = {camera.get_name(): camera for camera in group.cameras}
    rng = np.random.default_rng(2)
    for image in rec.images.values():
        camera = by_name[image.name.split("/")[0] + "_wide"]
        assert list(camera.get_size()) == [812, 617]
        assert type(camera).__name__ == ("FisheyeCamera" if image.camera.model.name in FISHEYE else "Camera")
        world = points_in_view(image, rng)
        projected = camera.project(world).reshape(-1, 2)
        np.testing.assert_allclose(projected, expected_opencv_pixels(image, world), atol=1e-6, rtol=0)


def test_toml_keeps_camera_order_beyond_ten(tmp_path):
    """aniposelib sorts table names: cam_10 before cam_2 unless the index is zero-padded."""
    rec = pycolmap.Reconstruction()
    rng = np.random.default_rng(3)
    for camera_id in range(1, 13):
        camera = pycolmap.Camera.create_from_model_name(camera_id, "OPENCV", 1.0, 812, 617)
        camera.params = MODELS["OPENCV"]
        rec.add_camera_with_trivial_rig(camera)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(image_id=camera_id, name=f"r{camera_id:02d}/narrow/f0.png", camera_id=camera_id),
            random_pose(rng))
    (path,) = write_toml(rec, tmp_path, sensors=("narrow",))
    names = [camera.get_name() for camera in CameraGroup.load(str(path)).cameras]
    assert names == [f"r{i:02d}_narrow" for i in range(1, 13)]
    assert "[cam_00]" in path.read_text()


def test_fisheye_refused_for_easymocap_but_written_for_aniposelib(tmp_path):
    rec = make_reconstruction({"OPENCV_FISHEYE": MODELS["OPENCV_FISHEYE"]})
    with pytest.raises(InputError, match="fisheye.*toml"):
        write_opencv(rec, tmp_path / "yml")
    (path,) = write_toml(rec, tmp_path / "toml")
    assert tomllib.loads(path.read_text())["cam_0"]["fisheye"] is True


@pytest.mark.parametrize("model", ["FOV", "THIN_PRISM_FISHEYE", "SIMPLE_DIVISION"])
def test_models_without_opencv_equivalent_are_refused(model):
    camera = pycolmap.Camera.create_from_model_name(1, model, 500.0, 812, 617)
    with pytest.raises(InputError, match=f"{model} has no OpenCV equivalent"):
        opencv_intrinsics(camera, "rig01_wide")


def test_principal_point_moves_by_half_a_pixel():
    camera = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 1.0, 812, 617)
    camera.params = [1000.0, 1001.0, 406.0, 308.5]
    k, dist, fisheye = opencv_intrinsics(camera)
    np.testing.assert_array_equal(k, [[1000.0, 0, 405.5], [0, 1001.0, 308.0], [0, 0, 1]])
    assert not fisheye and not dist.any()


def test_names_are_sanitised_and_numeric_names_stay_strings(tmp_path):
    rec = make_reconstruction({"OPENCV": MODELS["OPENCV"], "PINHOLE": MODELS["PINHOLE"]},
                              rig_names=["01", "rig.b"])
    cameras = read_easymocap(*write_opencv(rec, tmp_path))
    assert sorted(cameras) == ["01_wide", "rig_b_wide"]


def test_repeated_names_after_sanitising_are_refused(tmp_path):
    rec = make_reconstruction({"OPENCV": MODELS["OPENCV"], "PINHOLE": MODELS["PINHOLE"]},
                              rig_names=["rig.a", "rig_a"])
    with pytest.raises(InputError, match="repeat"):
        write_toml(rec, tmp_path)


def test_several_frames_export_their_mean_pose(tmp_path, caplog):
    """A camera of several frames is exported as their mean; where frames differ, one warning for all cameras (a
    recording's every camera said it on a line of its own)."""
    import logging

    rec = pycolmap.Reconstruction()
    base = random_pose(np.random.default_rng(4))
    tweak = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([4e-4, 0, 0, 1.0]) / np.linalg.norm([4e-4, 0, 0, 1.0])),
                             np.array([2e-4, 0, 0]))
    for rig in (1, 2, 3):
        camera = pycolmap.Camera.create_from_model_name(rig, "OPENCV", 1.0, 812, 617)
        camera.params = MODELS["OPENCV"]
        rec.add_camera_with_trivial_rig(camera)
        moved = tweak * tweak * base if rig == 2 else tweak * base
        for frame, pose in enumerate((base, moved)):
            rec.add_image_with_trivial_frame(pycolmap.Image(image_id=2 * rig + frame, name=f"rig0{rig}/wide/f{frame}.png",
                                                            camera_id=rig), pose)
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.camera_files"):
        group = CameraGroup.load(str(write_toml(rec, tmp_path)[0]))
    assert len(group.cameras) == 3
    centre = -cv2.Rodrigues(group.cameras[0].get_rotation())[0].T @ group.cameras[0].get_translation()
    expected = (rec.images[2].projection_center() + rec.images[3].projection_center()) / 2
    np.testing.assert_allclose(centre, expected, atol=1e-9)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and warnings[0].startswith("3 camera(s) have several frames") \
        and "rig02_wide, 2 frames" in warnings[0], warnings


def finished_workspace(root):
    """A workspace holding a finished result in the floor frame: the synthetic ring's model and narrow_poses."""
    from synthetic_world import ring

    from rigsfm.core.workspace import Workspace
    from rigsfm.run.deliver import write_model, write_narrow_poses
    from rigsfm.run.options import WorldOptions
    from rigsfm.run.world.frame import ground_maps, place_in_world

    rec = ring(seed=30, num_rigs=4).reconstruction
    world = place_in_world(rec, None, None, ["rig01"], WorldOptions())
    for point3D_id in list(rec.point3D_ids()):  # their observations are placeholders (pixel 0, 0)
        rec.delete_point3D(point3D_id)
    workspace = Workspace(root)
    workspace.prepare(overwrite=False)
    write_model(rec, workspace.sparse, overwrite=True)
    write_narrow_poses(rec, workspace.narrow_poses, metric=True, overwrite=True, world=world.to_dict(),
                       ground=ground_maps(rec, world.plane_heights))
    return pycolmap.Reconstruction(str(workspace.sparse))


@pytest.mark.parametrize("fmt", ["opencv", "toml"])
def test_rigsfm_export_writes_files_the_real_readers_project_like_the_model(tmp_path, fmt):
    from rigsfm.core.errors import WorkspaceError
    from rigsfm.inspect.export import MANIFEST, export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    rec = finished_workspace(tmp_path / "out")
    dest = export(tmp_path / "out", ExportOptions(format=ExportFormat(fmt)))
    assert dest == tmp_path / "out" / "export" / fmt
    rng = np.random.default_rng(5)
    images = [im for im in rec.images.values() if im.has_pose]
    if fmt == "opencv":
        cameras = read_easymocap(dest / "intri.yml", dest / "extri.yml")
        project = {name: (lambda p, c=c: cv2.projectPoints(p, c["Rvec"], c["T"], c["K"], c["dist"])[0].reshape(-1, 2))
                   for name, c in cameras.items()}
    else:
        group = CameraGroup.load(str(dest / "calibration.toml"))
        assert group.metadata["world"].startswith("floor frame: z up, normal to the floor")
        project = {c.get_name(): (lambda p, c=c: c.project(p).reshape(-1, 2)) for c in group.cameras}
    assert sorted(project) == sorted(im.name.split("/")[0] + "_" + im.name.split("/")[1] for im in images)
    for image in images:
        world = points_in_view(image, rng, 20)
        projected = project[image.name.split("/")[0] + "_" + image.name.split("/")[1]](world)
        np.testing.assert_allclose(projected, expected_opencv_pixels(image, world), atol=1e-6, rtol=0)
    assert (dest / MANIFEST).is_file()
    with pytest.raises(WorkspaceError, match="--overwrite"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat(fmt)))


def test_wildtrack_calibration_reads_and_projects_floor_points_like_mvdet(tmp_path):
    """Read the export the way MVDet's Wildtrack loader does and project floor points like its
    get_imagecoord_from_worldcoord (support.mvdet_floor_pixels)."""
    from support import mvdet_floor_pixels, rigsfm_floor_pixels

    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    rec = finished_workspace(tmp_path / "out")
    dest = export(tmp_path / "out", ExportOptions(format=ExportFormat.WILDTRACK))
    narrow = {im.name.split("/")[0]: im for im in rec.images.values() if im.has_pose and "/narrow/" in im.name}
    assert sorted(p.name for p in (dest / "calibrations" / "intrinsic_zero").iterdir()) == \
        [f"intr_{rig}.xml" for rig in sorted(narrow)]
    floor_m = np.array([[x, y] for x in np.linspace(-2, 2, 5) for y in np.linspace(-2, 2, 5)])
    for rig, image in narrow.items():
        mvdet = mvdet_floor_pixels(dest / "calibrations", rig, floor_m)
        ours = rigsfm_floor_pixels(image, floor_m)
        seen = ours[:, 1] > -1e4
        assert np.max(np.abs(mvdet[seen] - ours[seen])) < 0.05  # float32, as the loader reads them


def test_wildtrack_export_says_when_the_world_is_not_metric_on_the_floor(tmp_path, caplog):
    """The XML files carry no units or frame: a loader takes them for centimetres with the floor at z = 0, so an
    export of another world is named in a warning; --images with another format is refused, not ignored."""
    import json
    import logging

    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    finished_workspace(tmp_path / "out")
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.export"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat.WILDTRACK))
    assert not [r for r in caplog.records if "WILDTRACK" in r.getMessage()]
    poses_path = tmp_path / "out" / "narrow_poses.json"
    poses = json.loads(poses_path.read_text())
    poses_path.write_text(json.dumps({**poses, "metric": False, "world": {"frame": "mapping"}}))
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.export"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat.WILDTRACK, overwrite=True))
    warned = [r.getMessage() for r in caplog.records if "WILDTRACK" in r.getMessage()]
    assert len(warned) == 1 and "not metric" in warned[0] and "not in the floor frame" in warned[0]
    with pytest.raises(InputError, match="--format wildtrack only"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat.JSON, images=True))
    assert not (tmp_path / "out" / "export" / "json").exists()


def test_wildtrack_images_and_calibrations_name_a_rig_alike(tmp_path):
    """Rig names may hold spaces: the calibration files took the name OpenCV's keys allow (intr_rig_01.xml) and the
    images the rig's own (Image_subsets/rig 01/), so a loader pairing them by camera name found no images."""
    from rigsfm.inspect.camera_files import write_wildtrack

    rec = make_reconstruction({"PINHOLE": MODELS["PINHOLE"], "OPENCV": MODELS["OPENCV"]}, rig_names=["rig 01", "rig 02"])
    for image in list(rec.images.values()):  # the narrow images, as the export writes only those
        image.name = image.name.replace("/wide/", "/narrow/")
        path = tmp_path / "images" / image.name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), np.full((617, 812), 128, np.uint8))
    write_wildtrack(rec, tmp_path / "wildtrack", tmp_path / "images")
    cameras = sorted(p.stem.removeprefix("intr_") for p in (tmp_path / "wildtrack" / "calibrations" /
                                                             "intrinsic_zero").iterdir())
    assert cameras == ["rig_01", "rig_02"]
    assert sorted(p.name for p in (tmp_path / "wildtrack" / "Image_subsets").iterdir()) == cameras


@pytest.mark.parametrize("fmt", ["opencv", "toml", "nerfstudio", "json"])  # (open3d: this model has no points)
def test_an_export_of_a_result_without_scale_says_it_is_not_metres(tmp_path, caplog, fmt):
    """EasyMocap, aniposelib, nerfstudio (and Open3D) users take the files for metres, as the docs promise them: a
    result without scale was exported in the mapper's arbitrary unit without a word (only WILDTRACK warned)."""
    import json
    import logging

    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    finished_workspace(tmp_path / "out")
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.export"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat(fmt)))
    assert not [r for r in caplog.records if "NOT METRIC" in r.getMessage()]
    poses_path = tmp_path / "out" / "narrow_poses.json"
    poses_path.write_text(json.dumps({**json.loads(poses_path.read_text()), "metric": False}))
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.export"):
        export(tmp_path / "out", ExportOptions(format=ExportFormat(fmt), overwrite=True))
    (warned,) = [r.getMessage() for r in caplog.records if "NOT METRIC" in r.getMessage()]
    assert f"so the {fmt} export's positions are in the mapper's arbitrary unit" in warned


def test_the_json_export_says_what_its_numbers_are_in(tmp_path):
    """poses.json of `export --format json` held poses and cameras but not whether they are metres, nor the world
    frame (narrow_poses.json's metric, units and world): a reader of the export alone could not tell."""
    import json

    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    finished_workspace(tmp_path / "out")
    poses = json.loads((export(tmp_path / "out", ExportOptions(format=ExportFormat.JSON)) / "poses.json").read_text())
    narrow = json.loads((tmp_path / "out" / "narrow_poses.json").read_text())
    assert poses["metric"] is True and poses["units"] == narrow["units"] and poses["world"] == narrow["world"]
    assert poses["world"]["frame"] == "floor" and len(poses["images"]) > 0


def test_wildtrack_images_of_frames_the_run_was_not_given(tmp_path, caplog):
    """A recording beside the run's images, associated with `rigsfm associate --poses-from FRAME` (static rigs):
    `export --format wildtrack --images` wrote only the run's own frame, without a word, so MVDet-family tools got one
    frame of the recording. It now names the frames left out, and with --poses-from FRAME writes them too,
    undistorted with the run's cameras."""
    import json
    import logging

    from typer.testing import CliRunner

    from rigsfm.cli import app
    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    out, images = tmp_path / "out", tmp_path / "images"
    rec = finished_workspace(out)
    narrow = sorted((im for im in rec.images.values() if "/narrow/" in im.name), key=lambda im: im.name)
    frame = narrow[0].name.split("/")[-1]
    rigs = [im.name.split("/")[0] for im in narrow]
    rng = np.random.default_rng(0)
    for image in narrow:
        pixels = rng.integers(0, 255, (image.camera.height, image.camera.width), dtype=np.uint8)
        for name in (image.name, image.name.replace(frame, "later.png")):  # the same picture in both frames
            (images / name).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(images / name), pixels)
    (out / "summary.json").write_text(json.dumps({"inputs": {"images": str(images)}}))

    def written(dest):
        return sorted(p.relative_to(dest / "Image_subsets").as_posix() for p in (dest / "Image_subsets").rglob("*"))

    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.export"):
        dest = export(out, ExportOptions(format=ExportFormat.WILDTRACK, dest=tmp_path / "w1", images=True))
    stem = frame.rsplit(".", 1)[0]
    assert written(dest) == sorted([*rigs, *(f"{rig}/{stem}.png" for rig in rigs)])
    assert f"{len(rigs)} narrow image(s) of 1 frame(s) the run was not given (later.png)" in caplog.text
    assert f"--poses-from {frame}" in caplog.text

    result = CliRunner().invoke(app, ["export", str(out), "--format", "wildtrack", "--images", "--poses-from", frame,
                                      "--dest", str(tmp_path / "w2")])
    assert result.exit_code == 0, result.output
    lent = tmp_path / "w2"
    assert written(lent) == sorted([*rigs, *(f"{rig}/{s}.png" for rig in rigs for s in (stem, "later"))])
    for rig in rigs:  # undistorted exactly as the run's own frame: its camera
        assert (lent / "Image_subsets" / rig / "later.png").read_bytes() == \
            (lent / "Image_subsets" / rig / f"{stem}.png").read_bytes()
    with pytest.raises(InputError, match="--poses-from 'nope.png' is not a frame of this run"):
        export(out, ExportOptions(format=ExportFormat.WILDTRACK, dest=tmp_path / "w3", images=True,
                                  poses_from="nope.png"))
    with pytest.raises(InputError, match="--poses-from needs --images"):
        export(out, ExportOptions(format=ExportFormat.WILDTRACK, dest=tmp_path / "w4", poses_from=frame))
    cv2.imwrite(str(images / narrow[0].name.replace(frame, "later.png")), np.zeros((100, 120), np.uint8))
    with pytest.raises(InputError, match=r"later.png is 120x100 px, its camera rig01_narrow"):
        export(out, ExportOptions(format=ExportFormat.WILDTRACK, dest=tmp_path / "w5", images=True, poses_from=frame))
