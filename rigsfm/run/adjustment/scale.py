"""Metric scale from scale.yaml: a weighted least-squares scale factor over every measurement.

Each measurement i gives a model length L_i for a true length M_i. Its uncertainty combines the
measurement's own ``sigma`` with the model length's uncertainty (for a known length: the pixel noise
of its end points propagated through triangulation). The scale minimises sum(w_i (s L_i - M_i)^2),
w_i = 1 / sigma_i^2, and its standard uncertainty is 1 / sqrt(sum(w_i L_i^2)).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.errors import ReconstructionError
from rigsfm.run.inputs.scale_file import KnownLength, ScaleSpec

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Measurement:
    """One scale measurement: its true length and the same length in the model."""

    kind: str  # "camera_distance" or "known_length"
    label: str
    meters: float
    model_length: float
    sigma: float  # of the true length (metres)
    model_sigma: float = 0.0  # of the model length (model units)


@dataclass(frozen=True)
class ScaleEstimate:
    metres_per_unit: float
    sigma: float  # standard uncertainty of metres_per_unit
    measurements: tuple[Measurement, ...]
    unused: tuple[str, ...] = ()  # measurements that name unregistered cameras: "<label>: <why>"

    @property
    def relative_sigma_percent(self) -> float:
        return 100.0 * self.sigma / self.metres_per_unit

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
                    "sigma_meters": float(np.hypot(m.sigma, self.metres_per_unit * m.model_sigma)),
                }
            )
        return rows


class UnusableMeasurement(Exception):
    """A measurement that names cameras or images the reconstruction does not hold."""


def camera_centre(reconstruction: pycolmap.Reconstruction, camera: str) -> np.ndarray:
    """Centre of ``<rig>/<sensor>`` (mean over its registered frames) or of one image name."""
    centres = [
        image.projection_center()
        for image in reconstruction.images.values()
        if image.has_pose and (image.name == camera or image.name.startswith(camera + "/"))
    ]
    if not centres:
        raise UnusableMeasurement(f"{camera} was not registered")
    return np.mean(centres, axis=0)


def triangulate_in_images(reconstruction: pycolmap.Reconstruction,
                          observations: list[tuple[pycolmap.Image, np.ndarray]]) -> np.ndarray | None:
    """Triangulate one world point from ``(posed image, xy)`` observations (None if fewer than two)."""
    poses, rays = [], []
    for image, xy in observations:
        camera = reconstruction.cameras[image.camera_id]
        ray = np.asarray(camera.cam_ray_from_img(np.asarray([xy], dtype=np.float64))).reshape(3)
        poses.append(image.cam_from_world().matrix())
        rays.append(ray / np.linalg.norm(ray))
    if len(poses) < 2:
        return None
    point = pycolmap.triangulate_multi_view_point(poses, np.asarray(rays))
    return None if point is None else np.asarray(point).reshape(3)


def triangulate_observed_point(reconstruction: pycolmap.Reconstruction, observations) -> np.ndarray | None:
    """Triangulate one world point from ``(image name, xy)`` observations in registered images."""
    by_name = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    return triangulate_in_images(reconstruction, [(by_name[name], xy) for name, xy in observations if name in by_name])


def known_length_in_model(reconstruction: pycolmap.Reconstruction, item: KnownLength,
                          pixel_sigma: float) -> tuple[float, float]:
    """The object's length in model units and its uncertainty from ``pixel_sigma`` on every end point."""

    registered = {image.name for image in reconstruction.images.values() if image.has_pose}
    seen = sorted({o.image for o in item.observations} & registered)
    if len(seen) < 2:
        missing = sorted({o.image for o in item.observations} - registered)
        raise UnusableMeasurement(f"fewer than two of its images were registered ({', '.join(missing)} not)")

    def length(observations) -> float:
        ends = []
        for end, label in ((0, "a"), (1, "b")):
            point = triangulate_observed_point(reconstruction, [(name, ab[end]) for name, ab in observations])
            if point is None:
                raise UnusableMeasurement(f"its end {label} does not triangulate from {', '.join(seen)} (the rays "
                                          "do not meet in front of the cameras): check that a and b mark the same "
                                          "physical points in every image")
            ends.append(point)
        return float(np.linalg.norm(ends[0] - ends[1]))

    observations = [(o.image, [np.array(o.a), np.array(o.b)]) for o in item.observations]
    nominal = length(observations)
    variance = 0.0
    for k, end, axis in itertools.product(range(len(observations)), (0, 1), (0, 1)):
        shifted = [(name, [xy.copy() for xy in ab]) for name, ab in observations]
        shifted[k][1][end][axis] += pixel_sigma
        variance += (length(shifted) - nominal) ** 2
    return nominal, float(np.sqrt(variance))


def estimate_scale(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec) -> ScaleEstimate:
    """Metres per model unit from every usable measurement, weighted by its uncertainty. Measurements that
    name unregistered cameras are left out (listed in ``unused``); none usable raises ReconstructionError."""
    measurements, unused = [], []
    for d in spec.camera_distances:
        label = f"{d.a} - {d.b}"
        try:
            length = float(np.linalg.norm(camera_centre(reconstruction, d.a) - camera_centre(reconstruction, d.b)))
        except UnusableMeasurement as why:
            unused.append(f"{label}: {why}")
            continue
        measurements.append(Measurement("camera_distance", label, d.meters, length, d.sigma))
    for i, item in enumerate(spec.known_lengths):
        label = f"known_length[{i}]"
        try:
            length, model_sigma = known_length_in_model(reconstruction, item, spec.pixel_sigma)
        except UnusableMeasurement as why:
            unused.append(f"{label} ({item.meters} m): {why}")
            continue
        measurements.append(Measurement("known_length", label, item.meters, length, item.sigma, model_sigma))
    if not measurements:
        raise ReconstructionError(
            f"no measurement of {spec.path} can set the scale: {'; '.join(unused)}. Measure between cameras "
            "that register, or observe the known length in images that do"
        )
    for row in unused:
        logger.warning("Scale measurement left out: %s", row)
    lengths = np.array([m.model_length for m in measurements])
    meters = np.array([m.meters for m in measurements])
    zero = [m.label for m in measurements if m.model_length <= 1e-12 * max(1.0, float(lengths.max()))]
    if zero:
        raise ReconstructionError(f"scale measurement(s) {', '.join(zero)} of {spec.path} have zero length in the "
                                  "model (the same camera twice, or a bar whose two ends are one point); fix or "
                                  "remove them")
    first_guess = float(np.median(meters / lengths))
    sigmas = np.array([np.hypot(m.sigma, first_guess * m.model_sigma) for m in measurements])
    weights = 1.0 / sigmas**2
    scale = float(np.sum(weights * lengths * meters) / np.sum(weights * lengths**2))
    sigma = float(1.0 / np.sqrt(np.sum(weights * lengths**2)))
    estimate = ScaleEstimate(scale, sigma, tuple(measurements), tuple(unused))
    for residual in estimate.residuals():
        logger.info("Scale %s: %.4f m vs %.4f m (%+.3f %%, sigma %.4f m)", residual["label"],
                    residual["reconstructed_meters"], residual["meters"], residual["residual_percent"],
                    residual["sigma_meters"])
    return estimate
