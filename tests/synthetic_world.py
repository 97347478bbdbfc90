"""Small synthetic reconstructions with a known floor (z = 0 in the 'truth' world), for unit tests.

``ring(...)`` builds rigs on a circle (wide = reference sensor, narrow pitched further down, 6 cm apart) looking
at the centre, and sparse points on the floor, the surrounding wall, box tops and pillar sides; then moves
everything by ``model_from_truth`` (a rigid transform) so the floor is tilted and off the origin, as in a
mapper's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

WIDTH, HEIGHT = 812, 617


def add_hybrid_rig(rec: pycolmap.Reconstruction, rig_id: int, name: str, wide: pycolmap.Camera,
                   narrow: pycolmap.Camera, narrow_from_wide: pycolmap.Rigid3d, rig_from_world: pycolmap.Rigid3d,
                   points2D: dict[str, list[np.ndarray]], frame_file: str = "frame0000.png") -> list[pycolmap.Image]:
    """Add to ``rec`` the two cameras, a rig ``rig_id`` (wide its reference sensor, narrow at ``narrow_from_wide``),
    its frame ``rig_id`` at ``rig_from_world`` and the images ``NAME/<sensor>/FRAME_FILE`` (ids ``2 rig_id - 1``
    wide, ``2 rig_id`` narrow) holding ``points2D[sensor]``; returns the two images, wide first."""
    rec.add_camera(wide)
    rec.add_camera(narrow)
    sensors = {sensor: pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam.camera_id)
               for sensor, cam in (("wide", wide), ("narrow", narrow))}
    rig = pycolmap.Rig(rig_id=rig_id)
    rig.add_ref_sensor(sensors["wide"])
    rig.add_sensor(sensors["narrow"], narrow_from_wide)
    rec.add_rig(rig)
    frame = pycolmap.Frame(frame_id=rig_id, rig_id=rig_id, rig_from_world=rig_from_world)
    images = []
    for sensor in ("wide", "narrow"):
        image = pycolmap.Image(image_id=2 * rig_id - (sensor == "wide"), name=f"{name}/{sensor}/{frame_file}",
                               camera_id=sensors[sensor].id, frame_id=rig_id)
        if points2D.get(sensor):
            image.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in points2D[sensor]])
        images.append(image)
        frame.add_data_id(pycolmap.data_t(sensors[sensor], image.image_id))
    rec.add_frame(frame)
    for image in images:
        rec.add_image(image)
    return images


def look_at(centre: np.ndarray, target: np.ndarray, roll_deg: float = 0.0) -> pycolmap.Rigid3d:
    """cam_from_world for a camera at ``centre`` looking at ``target`` with z up in the world."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    right, down = c * right + s * down, -s * right + c * down
    rotation = np.stack([right, down, forward])  # rows: camera axes in the world
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)


def random_rigid(rng: np.random.Generator, translation: float = 10.0) -> pycolmap.Rigid3d:
    q = rng.normal(size=4)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(q / np.linalg.norm(q)), rng.uniform(-translation, translation, 3))


@dataclass
class World:
    reconstruction: pycolmap.Reconstruction  # in the model frame
    model_from_truth: pycolmap.Rigid3d
    truth_heights: dict[str, float]  # image name -> camera height above the floor
    narrow_from_wide: pycolmap.Rigid3d


def ring(*, seed: int = 0, num_rigs: int = 8, radius: float = 15.0, floor_points: int = 600,
         floor_noise: float = 0.005, wall_points: int = 1500, box_points: int = 60, pillar_points: int = 200,
         ceiling_points: int = 0, same_direction: bool = False, roll_deg: float = 0.5,
         model_from_truth: pycolmap.Rigid3d | None = None, narrow_model: str = "OPENCV") -> World:
    rng = np.random.default_rng(seed)
    model_from_truth = model_from_truth or random_rigid(rng)
    rec = pycolmap.Reconstruction()
    narrow_from_wide = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.087, 0.0, 0.0, 0.996]) / np.linalg.norm([0.087, 0, 0, 0.996])),
                                        np.array([-0.06, 0.0, 0.0]))
    truth_heights, image_ids = {}, []
    points = []
    r = np.sqrt(rng.uniform(2.0**2, 26.0**2, floor_points))
    a = rng.uniform(0, 2 * np.pi, floor_points)
    points.append(np.c_[r * np.cos(a), r * np.sin(a), rng.normal(0, floor_noise, floor_points)])
    a = rng.uniform(0, 2 * np.pi, wall_points)
    points.append(np.c_[28.0 * np.cos(a), 28.0 * np.sin(a), rng.uniform(0, 12.0, wall_points)])
    for bx, by, bz in ((20.0, 3.0, 1.0), (-19.0, 8.0, 1.2), (5.0, -21.0, 0.8)):
        points.append(np.c_[bx + rng.uniform(-0.6, 0.6, box_points), by + rng.uniform(-0.6, 0.6, box_points),
                            np.full(box_points, bz) + rng.normal(0, 0.003, box_points)])
    a = rng.uniform(0, 2 * np.pi, pillar_points)
    points.append(np.c_[-21.0 + 0.5 * np.cos(a), -10.0 + 0.5 * np.sin(a), rng.uniform(0, 8.0, pillar_points)])
    if ceiling_points:
        points.append(np.c_[rng.uniform(-25, 25, ceiling_points), rng.uniform(-25, 25, ceiling_points),
                            np.full(ceiling_points, 9.0)])
    points = np.vstack(points)
    for index in range(num_rigs):
        rig_id = index + 1
        angle = 2 * np.pi * index / num_rigs
        centre = np.array([radius * np.cos(angle), radius * np.sin(angle), 3.5 + rng.uniform(-0.25, 0.25)])
        target = np.array([0.0, 0.0, 0.0]) if not same_direction else centre + np.array([-10.0, 0.0, -2.2])
        if same_direction:
            centre = np.array([radius, -15.0 + 30.0 * index / max(num_rigs - 1, 1), centre[2]])
            target = centre + np.array([-10.0, 0.0, -2.2])
        wide_from_truth = look_at(centre, target, rng.normal(0, roll_deg))
        wide = pycolmap.Camera.create_from_model_name(2 * rig_id - 1, "OPENCV", 1.0, WIDTH, HEIGHT)
        wide.params = [450.0, 450.0, 406.0, 308.5, -0.1, 0.01, 0.0, 0.0]
        narrow = pycolmap.Camera.create_from_model_name(2 * rig_id, narrow_model, 1.0, WIDTH, HEIGHT)
        narrow.params = {"OPENCV": [1800.0, 1800.0, 406.0, 308.5, -0.01, 0.0, 0.0, 0.0],
                         "PINHOLE": [1800.0, 1800.0, 406.0, 308.5]}[narrow_model]
        # the first rig's two images hold one observation of every point (tracks of length 2)
        observed = [np.zeros(2)] * len(points) if rig_id == 1 else []
        images = add_hybrid_rig(rec, rig_id, f"rig{rig_id:02d}", wide, narrow, narrow_from_wide,
                                wide_from_truth * model_from_truth.inverse(), {"wide": observed, "narrow": observed})
        image_ids.extend(image.image_id for image in images)
        truth_heights[images[0].name] = float(centre[2])
        narrow_centre = (narrow_from_wide * wide_from_truth).inverse().translation
        truth_heights[images[1].name] = float(narrow_centre[2])

    for k, p in enumerate(points):
        track = pycolmap.Track()
        track.add_element(int(image_ids[0]), k)
        track.add_element(int(image_ids[1]), k)
        rec.add_point3D(model_from_truth * p, track, np.zeros(3, np.uint8))
    return World(rec, model_from_truth, truth_heights, narrow_from_wide)


def straight_down_camera(height: float, focal: float = 1000.0, model: str = "PINHOLE") -> pycolmap.Reconstruction:
    """One camera at (0, 0, height) looking straight down (image x = world x, image y = world -y)."""
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, model, focal, WIDTH, HEIGHT)
    if model == "PINHOLE":
        camera.params = [focal, focal, WIDTH / 2, HEIGHT / 2]
    rec.add_camera_with_trivial_rig(camera)
    rotation = np.diag([1.0, -1.0, -1.0])
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ np.array([0.0, 0.0, height]))
    rec.add_image_with_trivial_frame(pycolmap.Image(image_id=1, name="rig01/narrow/f0.png", camera_id=1), pose)
    return rec
