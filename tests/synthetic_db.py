"""A hybrid-rig network as a COLMAP database with exact ground truth, from pycolmap.synthesize_dataset.

pycolmap synthesizes rigs of two sensors (poses, 3D points). We give each rig its own wide and narrow
intrinsics (narrow focal 4x the wide one), rename images to the rigsfm layout, and write the database
ourselves: wide images get the noisy projections of the points as keypoints and exact matches; narrow
images get no keypoints, as in a homogeneous scene.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.geometry import project_world
from rigsfm.core.rig import RigCalibration
from rigsfm.run.inputs.database import rig_configs
from rigsfm.run.inputs.images import ImageEntry


@dataclass
class SyntheticNetwork:
    database: Path
    ground_truth: pycolmap.Reconstruction
    rigs: list[RigCalibration]
    images: list[ImageEntry]


def make_network(root: Path, num_rigs: int = 4, seed: int = 0, noise_px: float = 0.5,
                 num_points: int = 600, narrow_observations: bool = False) -> SyntheticNetwork:
    rng = np.random.default_rng(seed)
    pycolmap.set_random_seed(seed)
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=num_rigs, num_cameras_per_rig=2, num_frames_per_rig=1, num_points3D=num_points,
        camera_model_id=pycolmap.CameraModelId.OPENCV, camera_width=1024, camera_height=768,
        camera_params=[800.0, 800.0, 512.0, 384.0, 0.0, 0.0, 0.0, 0.0],
        sensor_from_rig_translation_stddev=0.05, sensor_from_rig_rotation_stddev=3.0,
    )
    synthetic = pycolmap.synthesize_dataset(options)

    rigs, images, names = [], [], {}
    for index, rig in enumerate(sorted(synthetic.rigs.values(), key=lambda r: r.rig_id), start=1):
        name = f"rig{index:02d}"
        (narrow_sensor, narrow_from_wide), = rig.non_ref_sensors.items()
        wide_f, narrow_f = 700.0 + 20.0 * index, 2800.0 + 50.0 * index
        wide = pycolmap.Camera(model="OPENCV", width=1024, height=768,
                               params=[wide_f, wide_f * 1.001, 510.0 + index, 385.0 - index, -0.08, 0.01, 1e-4, -1e-4])
        narrow = pycolmap.Camera(model="OPENCV", width=1024, height=768,
                                 params=[narrow_f, narrow_f, 512.5, 383.0, -0.01, 0.0, 0.0, 0.0])
        rigs.append(RigCalibration(name, wide, narrow, narrow_from_wide))
        for sensor, sensor_id, camera in (("wide", rig.ref_sensor_id, wide), ("narrow", narrow_sensor, narrow)):
            gt_camera = synthetic.cameras[sensor_id.id]
            gt_camera.params = camera.params
            gt_camera.model = camera.model
            names[sensor_id.id] = f"{name}/{sensor}/frame0000.png"
            images.append(ImageEntry(name, sensor, "frame0000.png", root / "images" / names[sensor_id.id]))
    for image in synthetic.images.values():
        image.name = names[image.camera_id]

    point_ids = np.array(sorted(synthetic.points3D))
    xyz = np.array([synthetic.points3D[i].xyz for i in point_ids])
    database_path = root / "database.db"
    with pycolmap.Database.open(database_path) as database:
        for camera in synthetic.cameras.values():
            camera.has_prior_focal_length = True
            database.write_camera(camera, use_camera_id=True)
        keypoint_of: dict[int, dict[int, int]] = {}
        for image in sorted(synthetic.images.values(), key=lambda im: im.image_id):
            database.write_image(pycolmap.Image(name=image.name, camera_id=image.camera_id,
                                                image_id=image.image_id), use_image_id=True)
            if "/narrow/" in image.name and not narrow_observations:
                database.write_keypoints(image.image_id, np.zeros((0, 2), dtype=np.float32))
                continue
            camera = synthetic.cameras[image.camera_id]
            xy, inside = project_world(camera, image.cam_from_world(), xyz)
            xy = xy[inside] + rng.normal(0.0, noise_px, size=(inside.sum(), 2))
            database.write_keypoints(image.image_id, xy.astype(np.float32))
            keypoint_of[image.image_id] = {int(pid): k for k, pid in enumerate(point_ids[inside])}
        for id1, id2 in itertools.combinations(sorted(keypoint_of), 2):
            common = sorted(set(keypoint_of[id1]) & set(keypoint_of[id2]))
            matches = np.array([[keypoint_of[id1][p], keypoint_of[id2][p]] for p in common], dtype=np.uint32)
            database.write_matches(id1, id2, matches)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.inlier_matches = matches
            database.write_two_view_geometry(id1, id2, geometry)
        database.clear_rigs()
        database.clear_frames()
        pycolmap.apply_rig_config(rig_configs(rigs, images), database)
    return SyntheticNetwork(database_path, synthetic, rigs, images)


def perturbed_model(ground_truth: pycolmap.Reconstruction, seed: int, narrow_observations: bool = False,
                    scale: float = 0.37) -> pycolmap.Reconstruction:
    """A deterministic stand-in for a mapped model (no mapper run): ``ground_truth`` with every observation the exact
    projection of its point (through the rigs' own cameras) plus 0.5 px noise, rig poses and points moved (1 mrad,
    1 cm), then moved by a similarity of ``scale`` (arbitrary units, as the mapper leaves a model without narrow
    observations); narrow observations dropped unless ``narrow_observations``."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction(ground_truth)
    if not narrow_observations:
        for image in rec.images.values():
            if "/narrow/" in image.name:
                for k, point in enumerate(image.points2D):
                    if point.has_point3D():
                        rec.delete_observation(image.image_id, k)
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        camera = rec.cameras[image.camera_id]
        for point in image.points2D:
            if point.has_point3D():
                xyz = rec.points3D[point.point3D_id].xyz
                exact = np.asarray(camera.img_from_cam(image.cam_from_world() * xyz[None]))[0]
                point.xy = exact + rng.normal(0, 0.5, 2)
    for frame_id in sorted(rec.frames):
        frame = rec.frame(frame_id)
        pose = frame.rig_from_world
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(0, 1e-3, 3)) * pose.rotation,
                                                np.asarray(pose.translation) + rng.normal(0, 0.01, 3))
    for point_id in sorted(rec.points3D):
        rec.points3D[point_id].xyz = rec.points3D[point_id].xyz + rng.normal(0, 0.01, 3)
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, -3.0])))
    return rec
