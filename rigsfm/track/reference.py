"""The reference a rig is tracked against: its calibration and pose in OUT/sparse, and the map.

The map is the SIFT descriptors (from OUT/database.db) of every reference-image keypoint that has a
3D point in OUT/sparse, grouped per reference image ("blocks"); the points the narrow stage appended to the
narrow images (``rigsfm run --narrow``: guided matches, heads) have no descriptor and are left out, of the
baseline too, as a new frame has none. Changes are measured from each rig's
*baseline*: its reference wide image (and narrow image, if it observes map points) registered with the
same estimator from its own observations in the model. Bundle adjustment compromises a little between
all images, so the model's pose and the estimator's pose of the very same image differ by up to a few mm;
the baseline removes that bias, and the model pose is kept as ``wide_from_world``. Everything here pickles
cheaply to worker processes and Ray workers (numpy arrays and pycolmap's own cameras and poses).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import ReconstructionError, WorkspaceError
from rigsfm.core.names import ImageName, name_of
from rigsfm.core.workspace import Workspace, model_fingerprint
from rigsfm.run.inputs.database import damage
from rigsfm.track.options import RegistrationOptions
from rigsfm.track.pose import estimate_rig_pose, pose_covariance

logger = logging.getLogger(__name__)

DEFAULT_NEIGHBOURS = 2  # besides its own images, a rig is matched against its most covisible images


@dataclass(frozen=True)
class ReferenceRig:
    """One rig as calibrated and registered in the reference model (wide = reference sensor)."""

    name: str
    wide: pycolmap.Camera
    narrow: pycolmap.Camera | None  # None when the reference run had no narrow image of this rig
    narrow_from_wide: pycolmap.Rigid3d | None  # E^sl exactly as in OUT/sparse
    wide_from_world: pycolmap.Rigid3d  # the reference pose in OUT/sparse
    baseline_wide_from_world: pycolmap.Rigid3d  # changes are measured from this (see the module docstring)
    baseline_covariance: np.ndarray  # 6x6, see rigsfm.track.pose.pose_covariance
    reference_image: str
    blocks: tuple[int, ...]  # indices into ReferenceMap.blocks this rig's frames are matched against
    narrow_observes_map: bool  # the reference narrow image has 3D points: match new narrow images too

    def cameras(self) -> tuple[dict[str, pycolmap.Camera], dict[str, pycolmap.Rigid3d]]:
        """Per sensor: the calibrated camera and its fixed ``sensor_from_rig`` (wide: identity, narrow: E^sl)."""
        cameras = {"wide": self.wide}
        sensor_from_rig = {"wide": pycolmap.Rigid3d()}
        if self.narrow is not None:
            cameras["narrow"] = self.narrow
            sensor_from_rig["narrow"] = self.narrow_from_wide  # type: ignore[assignment]  # set with the narrow camera
        return cameras, sensor_from_rig


@dataclass(frozen=True)
class MapBlock:
    image: str
    descriptors: np.ndarray  # N x 128 uint8, as COLMAP stores SIFT
    xyz: np.ndarray  # N x 3 float64, metres (OUT/sparse)
    point3D_ids: np.ndarray  # N int64


@dataclass(frozen=True)
class ReferenceMap:
    rigs: dict[str, ReferenceRig]
    blocks: tuple[MapBlock, ...]
    fingerprint: str
    sparse: str = field(default="")


def _split_name(name: str) -> ImageName:
    try:
        return ImageName.parse(name)
    except ValueError:
        raise WorkspaceError(f"image {name!r} in the reference model is not named <rig>/<sensor>/<frame>") from None


def _reference_rigs(rec: pycolmap.Reconstruction) -> dict[str, dict]:
    """Per rig: its first registered wide image (by name), the cameras and E^sl from the model."""
    rigs: dict[str, dict] = {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        parsed = _split_name(image.name)
        rig_name, sensor = parsed.rig, parsed.sensor
        entry = rigs.setdefault(rig_name, {"wide": None, "narrow": None, "narrow_from_wide": None, "image": None})
        camera = rec.cameras[image.camera_id]
        if sensor == "wide" and entry["image"] is None and image.has_pose:
            entry["image"], entry["frame_id"] = image.name, image.frame_id
            entry["wide_from_world"] = image.cam_from_world()
        if entry[sensor] is None:
            entry[sensor] = copy.copy(camera)
            if sensor == "narrow":
                rig = rec.rigs[rec.frames[image.frame_id].rig_id]
                entry["narrow_from_wide"] = copy.copy(rig.sensor_from_rig(
                    pycolmap.sensor_t(pycolmap.SensorType.CAMERA, image.camera_id)))
    return rigs


def _covisible(rec: pycolmap.Reconstruction, names: list[str]) -> np.ndarray:
    """Number of 3D points shared by every pair of the named images."""
    index = {name: i for i, name in enumerate(names)}
    counts = np.zeros((len(names), len(names)), dtype=np.int64)
    for point in rec.points3D.values():
        seen = sorted({index[rec.images[el.image_id].name] for el in point.track.elements
                       if rec.images[el.image_id].name in index})
        for a in seen:
            for b in seen:
                counts[a, b] += 1
    return counts


def _observations(rec: pycolmap.Reconstruction, frame_id: int,
                  keypoints: dict[str, int]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per sensor of one reference frame: the 2D observations of 3D points and the points, of the database's
    keypoints only (``keypoints``: image name -> their count), as a new frame is registered."""
    found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for image in rec.images.values():
        if image.frame_id == frame_id and image.num_points3D > 0:
            points = [image.points2D[i] for i in image.get_observation_point2D_idxs()
                      if i < keypoints.get(image.name, 0)]
            if not points:
                continue
            found[name_of(image).sensor] = (np.array([p.xy for p in points], np.float64).reshape(-1, 2),
                                               np.array([rec.points3D[p.point3D_id].xyz for p in points]))
    return found


def baseline_pose(rig: ReferenceRig, observations: dict,
                  options: RegistrationOptions) -> tuple[pycolmap.Rigid3d, np.ndarray]:
    """The reference frame registered from its own observations, and that pose's covariance."""
    cameras, sensor_from_rig = rig.cameras()
    observations = {s: observations[s] for s in observations if s in cameras}
    estimate = estimate_rig_pose(observations, cameras, sensor_from_rig, options)
    if estimate is None:
        raise ReconstructionError(f"the reference image {rig.reference_image} cannot be registered against "
                                  "its own map points: the reference model is unusable for tracking")
    pose, inliers, used = estimate
    masks = np.split(inliers, np.cumsum([len(observations[s][0]) for s in used])[:-1])
    covariance = pose_covariance(pose, [(cameras[s], sensor_from_rig[s], observations[s][0][m], observations[s][1][m])
                                        for s, m in zip(used, masks)], pose.rotation.matrix())
    return pose, covariance


def load_reference(out: Path, neighbours: int = DEFAULT_NEIGHBOURS,
                   options: RegistrationOptions | None = None) -> ReferenceMap:
    """Read OUT/sparse and OUT/database.db into a picklable :class:`ReferenceMap`."""
    options = options or RegistrationOptions()
    workspace = Workspace(Path(out))
    workspace.require_result()
    if not workspace.database.is_file():
        raise WorkspaceError(f"'{workspace.database}' is missing: track needs the descriptors of the reference run")
    problem = damage(workspace.database)  # COLMAP's words for it are a full disk's
    if problem is not None:
        raise WorkspaceError(f"'{workspace.database}' {problem}: {workspace.rerun_hint}")
    rec = workspace.read_sparse()
    with_points = sorted((im for im in rec.images.values() if im.has_pose and im.num_points3D > 0),
                         key=lambda im: im.name)
    if not with_points:
        raise WorkspaceError(f"'{workspace.sparse}' has no 3D points to register new images against")
    blocks = []
    keypoints: dict[str, int] = {}  # per image: its first points2D are the database's keypoints
    with pycolmap.Database.open(workspace.database) as database:
        for image in with_points:
            db_image = database.read_image_with_name(image.name)
            if db_image is None or not database.exists_descriptors(db_image.image_id):
                if name_of(image).sensor == "narrow":
                    # the narrow stage's observations (guided matches, heads): appended, without descriptors
                    logger.info("%s: no descriptors (its observations are the narrow stage's), not in the map",
                                image.name)
                    continue
                raise WorkspaceError(f"{workspace.database} has no descriptors of {image.name} of the reference "
                                     "model; the database and sparse/ come from different runs")
            descriptors = np.asarray(database.read_descriptors(db_image.image_id).data)
            count = descriptors.shape[0]
            stored = np.asarray(database.read_keypoints(db_image.image_id), dtype=np.float64).reshape(count, -1)
            if count > image.num_points2D() or not np.allclose(
                    stored[:, :2], [image.points2D[i].xy for i in range(count)], atol=1e-3):
                raise WorkspaceError(f"{workspace.database}: descriptors of {image.name} do not match the model's "
                                     "keypoints; the database and sparse/ come from different runs")
            keypoints[image.name] = count
            idxs = np.asarray([i for i in image.get_observation_point2D_idxs() if i < count], dtype=np.int64)
            ids = np.array([image.points2D[i].point3D_id for i in idxs], dtype=np.int64)
            xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
            blocks.append(MapBlock(image.name, np.ascontiguousarray(descriptors[idxs]), xyz, ids))
    names = [b.image for b in blocks]
    covisible = _covisible(rec, names)
    rigs = {}
    for name, entry in _reference_rigs(rec).items():
        if entry["image"] is None:
            logger.warning("rig %s has no registered wide image in the reference model: it cannot be tracked", name)
            continue
        own = [i for i, n in enumerate(names) if ImageName.parse(n).rig == name]
        shared = covisible[own].sum(axis=0) if own else np.zeros(len(names))
        others = [i for i in np.argsort(-shared, kind="stable") if i not in own and shared[i] > 0]
        observations = _observations(rec, entry["frame_id"], keypoints)
        rig = ReferenceRig(
            name=name,
            wide=entry["wide"],
            narrow=entry["narrow"],
            narrow_from_wide=entry["narrow_from_wide"],
            wide_from_world=entry["wide_from_world"],
            baseline_wide_from_world=entry["wide_from_world"],
            baseline_covariance=np.zeros((6, 6)),
            reference_image=entry["image"],
            blocks=tuple(int(i) for i in (own + others[:neighbours]) or range(len(names))),
            narrow_observes_map="narrow" in observations,
        )
        baseline, covariance = baseline_pose(rig, observations, options)
        rigs[name] = replace(rig, baseline_wide_from_world=baseline, baseline_covariance=covariance)
    logger.info("Reference map: %d rigs, %d images, %d descriptors", len(rigs), len(blocks),
                sum(len(b.xyz) for b in blocks))
    return ReferenceMap(rigs, tuple(blocks), model_fingerprint(workspace.sparse), str(workspace.sparse))
