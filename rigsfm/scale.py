"""Metric scale from scale.yaml: a least-squares scale factor over every measurement, with residuals."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.errors import ReconstructionError
from rigsfm.scale_file import KnownLength, ScaleSpec

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Measurement:
    """One scale measurement: its true length and the same length in the model."""

    kind: str  # "camera_distance" or "known_length"
    label: str
    meters: float
    model_length: float


@dataclass(frozen=True)
class ScaleEstimate:
    metres_per_unit: float
    measurements: tuple[Measurement, ...]

    def residuals(self) -> list[dict]:
        """Per measurement: the metric length after scaling, and its error in metres and percent."""
        rows = []
        for m in self.measurements:
            scaled = self.metres_per_unit * m.model_length
            rows.append(
                {
                    "kind": m.kind,
                    "label": m.label,
                    "meters": m.meters,
                    "reconstructed_meters": scaled,
                    "residual_meters": scaled - m.meters,
                    "residual_percent": 100.0 * (scaled - m.meters) / m.meters,
                }
            )
        return rows


def camera_centre(reconstruction: pycolmap.Reconstruction, camera: str) -> np.ndarray:
    """Centre of ``<rig>/<sensor>`` (mean over its registered frames) or of one image name."""
    centres = [
        image.projection_center()
        for image in reconstruction.images.values()
        if image.has_pose and (image.name == camera or image.name.startswith(camera + "/"))
    ]
    if not centres:
        raise ReconstructionError(
            f"scale measurement names {camera}, which was not registered; remove it from scale.yaml"
        )
    return np.mean(centres, axis=0)


def triangulate_observed_point(reconstruction: pycolmap.Reconstruction, observations) -> np.ndarray | None:
    """Triangulate one world point from ``(image name, xy)`` observations in registered images."""
    by_name = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    poses, rays = [], []
    for name, xy in observations:
        image = by_name.get(name)
        if image is None:
            continue
        camera = reconstruction.cameras[image.camera_id]
        ray = np.asarray(camera.cam_ray_from_img(np.asarray([xy], dtype=np.float64))).reshape(3)
        poses.append(image.cam_from_world().matrix())
        rays.append(ray / np.linalg.norm(ray))
    if len(poses) < 2:
        return None
    point = pycolmap.triangulate_multi_view_point(poses, np.asarray(rays))
    return None if point is None else np.asarray(point).reshape(3)


def known_length_in_model(reconstruction: pycolmap.Reconstruction, item: KnownLength) -> float:
    ends = []
    for end in ("a", "b"):
        point = triangulate_observed_point(
            reconstruction, [(o.image, getattr(o, end)) for o in item.observations]
        )
        if point is None:
            raise ReconstructionError(
                f"known length of {item.meters} m: fewer than two of its images were registered; "
                "observe it in other images or remove it from scale.yaml"
            )
        ends.append(point)
    return float(np.linalg.norm(ends[0] - ends[1]))


def estimate_scale(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec) -> ScaleEstimate:
    """Metres per model unit minimising the sum of squared *relative* errors of all measurements."""
    measurements = []
    for d in spec.camera_distances:
        length = float(np.linalg.norm(camera_centre(reconstruction, d.a) - camera_centre(reconstruction, d.b)))
        measurements.append(Measurement("camera_distance", f"{d.a} - {d.b}", d.meters, length))
    for i, item in enumerate(spec.known_lengths):
        measurements.append(
            Measurement("known_length", f"known_length[{i}]", item.meters, known_length_in_model(reconstruction, item))
        )
    lengths = np.array([m.model_length for m in measurements])
    meters = np.array([m.meters for m in measurements])
    if np.any(lengths <= 1e-12):
        raise ReconstructionError("a scale measurement has zero length in the model (same camera twice?)")
    # minimise sum((s * L_i - M_i) / M_i)^2  =>  s = sum(L_i / M_i) / sum((L_i / M_i)^2)
    ratio = lengths / meters
    scale = float(np.sum(ratio) / np.sum(ratio**2))
    estimate = ScaleEstimate(scale, tuple(measurements))
    for row in estimate.residuals():
        logger.info("Scale %s: %.4f m vs %.4f m (%+.3f %%)", row["label"], row["reconstructed_meters"],
                    row["meters"], row["residual_percent"])
    return estimate
