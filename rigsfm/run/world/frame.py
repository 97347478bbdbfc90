"""Stage 7, world (after ``adjust``): the result in the analyst's world -- z = 0 on the floor, z up, metres.

``--world floor`` (default): the floor plane is found (:func:`rigsfm.run.world.floor.estimate_floor`: the sparse points
and the known-length markers, which lie on the floor, and only when they do not fix it precisely enough,
floor matches between the wide images through a plane-induced warp) and the model is moved into the floor
frame with a scale-1 similarity, so E^sl and the metres are untouched:

- z: the floor's upward normal; the floor is z = 0;
- origin: under the centroid of the rigs (mean wide-camera centre of each registered rig);
- x: horizontal, from the origin towards the first rig of rigs.yaml (the first registered one); y = z x x.

When no floor is found the mapper's frame is kept and the warning ``NO FLOOR FOUND`` says why and what to do.
``--world mapping`` keeps the mapper's frame (after the metric adjustment) without looking for a floor.

In the floor frame every narrow camera gets its ground maps (:func:`ground_maps`, written into
narrow_poses.json): ``ground_from_image`` on the floor and on ``--plane-height`` (e.g. 1.7 for heads), the
footprint polygon and the ground sampling distance at the footprint centre; pairs get the area both see.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.geometry import Plane
from rigsfm.core.ground import Footprint, coverage, footprints, ground_from_image, pairwise_overlaps
from rigsfm.core.names import ImageName, name_of, registered_narrow_images
from rigsfm.core.summary import WorldSummary
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.options import WorldFrame, WorldOptions
from rigsfm.run.world.analysis_floor import find_floor
from rigsfm.run.world.floor import (
    FloorEstimate,
    apply_floor_frame,
    estimate_floor,
    refit_floor,
    with_pose_uncertainty,
)
from rigsfm.run.world.floor_model import floor_markers, rig_positions

logger = logging.getLogger(__name__)

ORIGIN = "on the floor under the centroid of the rigs (mean wide-camera centre of each registered rig)"
X_AXIS = "horizontal, from the origin towards the first registered rig of rigs.yaml ({rig})"
Z_AXIS = "up, normal to the floor; z = 0 on the floor"
NO_FLOOR_HELP = "give known-length markers on the floor (scale.yaml), or --world mapping"
NO_FLOOR_WITH_MARKERS_HELP = ("check that scale.yaml's known lengths lie on the floor and add one away from the "
                              "others, or --world mapping")


def no_floor_warning(reason: str, markers: int) -> str:
    """The NO FLOOR FOUND warning: what to do depends on whether known-length markers were there to use
    (``markers``: their end points triangulated)."""
    help_ = NO_FLOOR_WITH_MARKERS_HELP if markers else NO_FLOOR_HELP
    return f"NO FLOOR FOUND: {reason}; the mapper's frame is kept: {help_}"


def validate_world_options(options: WorldOptions) -> None:
    """Refuse impossible world options before any heavy work (the camera heights are checked once the floor
    is known, :func:`check_plane_heights`)."""
    for height in options.plane_heights:
        if not np.isfinite(height):
            raise InputError(f"--plane-height {height} is not a height: give one above the floor in metres (e.g. 1.7 "
                             "for heads)")
        if height < 0:
            raise InputError(f"--plane-height {height:g} m is below the floor: give a height above it in metres "
                             "(e.g. 1.7 for heads)")
    if options.plane_heights and options.frame == WorldFrame.MAPPING:
        raise InputError("--plane-height needs the floor frame: leave out --world mapping")


def check_plane_heights(heights: Sequence[float], camera_heights: dict[str, float]) -> None:
    """Refuse a plane at or above a narrow camera (it would not see it)."""
    narrow = {n: h for n, h in camera_heights.items() if ImageName.parse(n).is_narrow}
    if not narrow:
        return
    lowest_name = min(narrow, key=narrow.get)  # type: ignore[arg-type]  # typeshed: get's overloads
    for height in heights:
        if height >= narrow[lowest_name]:
            raise InputError(
                f"--plane-height {height:g} m is above the narrow cameras (the lowest, {lowest_name}, is "
                f"{narrow[lowest_name]:.2f} m above the floor): give a height below it (e.g. 1.7 for heads); "
                "features and matches in OUT are reused by a re-run with --overwrite")


@dataclass
class WorldResult:
    """The frame the result is in and how it was found (``to_dict`` goes into narrow_poses.json and summary.json)."""

    asked: WorldFrame
    frame: WorldFrame  # the frame used: floor, or mapping (asked, or no floor found)
    estimate: FloorEstimate | None = None
    x_rig: str | None = None
    plane_heights: tuple[float, ...] = ()  # planes of the ground maps (0 = the floor first)
    metric: bool = True
    warnings: list[str] = field(default_factory=list)
    narrow_heights: dict[str, dict] | None = None  # :meth:`set_narrow_heights`'s

    def floor_plane(self) -> Plane | None:
        """The floor in the frame it was fitted in (before :meth:`apply`); None unless the floor frame was found."""
        if self.frame != WorldFrame.FLOOR:
            return None
        fit = self.estimate.fit  # type: ignore[union-attr]  # FLOOR: estimated
        return Plane(np.asarray(fit.normal, dtype=np.float64), float(fit.offset), int(fit.num_points))  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here

    def analysis_floor(self, reconstruction: pycolmap.Reconstruction,
                       scale: ScaleSpec | None) -> tuple[Plane | None, str]:
        """The floor the epipolar bands' analysis points lie on, in ``reconstruction``'s frame (before :meth:`apply`),
        and where it comes from: the floor fit (``floor_fit``), else :func:`find_floor`'s."""
        plane = self.floor_plane()
        return (plane, "floor_fit") if plane is not None else find_floor(reconstruction, scale)

    def refit(self, reconstruction: pycolmap.Reconstruction, scale: ScaleSpec | None) -> None:
        """Fit the floor again in ``reconstruction``, the model this frame was found in adjusted once more (the
        narrow stage's second adjustment), so the frame :meth:`apply` moves it into fits the delivered poses
        (:func:`rigsfm.run.world.floor.refit_floor`: no image read again). Nothing unless the floor frame was found."""
        if self.frame != WorldFrame.FLOOR:
            return
        self.estimate = refit_floor(self.estimate, reconstruction, floor_markers(reconstruction, scale),  # type: ignore[arg-type]  # FLOOR: estimated
                                    x_towards=self.x_rig)

    def add_pose_uncertainty(self, reconstruction: pycolmap.Reconstruction, covariance) -> None:
        """Widen the floor's normal sigma to the poses' covariance carried through the floor points where larger
        (:func:`rigsfm.run.world.floor.with_pose_uncertainty`); ``reconstruction`` before :meth:`apply`."""
        if self.frame == WorldFrame.FLOOR:
            self.estimate = with_pose_uncertainty(self.estimate, reconstruction, covariance)  # type: ignore[arg-type]  # FLOOR: estimated

    def set_narrow_heights(self, reconstruction: pycolmap.Reconstruction, own: dict) -> None:
        """Every registered narrow camera's height above the floor and its 1 sigma: the floor's part (the plane's
        covariance at that camera) and the camera's own vertical centre uncertainty relative to the network
        (``own``: the uncertainty stage's ``narrow``, covariances in the camera's axes), independent, so added in
        quadrature; or, where larger, the poses' covariance carried into the camera's height above the floor with both
        moved by the same poses (``pose_sigma_m``: the floor's tilt by the poses is levered to the camera, which the
        pairs' residuals miss, benchmarks/README.md) and the points' scatter in quadrature. ``reconstruction`` in the
        floor frame (after :meth:`apply`)."""
        if self.frame != WorldFrame.FLOOR:
            return
        fit = self.estimate.fit  # type: ignore[union-attr]  # FLOOR: estimated
        heights = {}
        for image in registered_narrow_images(reconstruction):
            floor_part = fit.camera_height_sigmas.get(image.name, float("nan"))  # type: ignore[union-attr]
            # None, not NaN, where the fit has no sigma for it: summary.json stays strict JSON
            entry = {"height_m": float(image.projection_center()[2]),
                     "floor_sigma_m": floor_part if np.isfinite(floor_part) else None}
            record = own.get(image.name)
            covariance = getattr(record, "centre_covariance_mm2", None)
            if covariance is not None:
                up = image.cam_from_world().rotation.matrix()[:, 2]  # the floor's z in the camera's axes
                own_sigma = float(np.sqrt(max(up @ np.asarray(covariance) @ up, 0.0))) / 1000.0
                entry["own_sigma_m"] = own_sigma
                if np.isfinite(floor_part):
                    entry["sigma_m"] = float(np.hypot(floor_part, own_sigma))
            pose_part = fit.pose_camera_height_sigmas.get(image.name)  # type: ignore[union-attr]
            if pose_part is not None and np.isfinite(fit.scatter_height_sigma):  # type: ignore[union-attr]
                pose_sigma = float(np.hypot(pose_part, fit.scatter_height_sigma))  # type: ignore[union-attr]
                entry["pose_sigma_m"] = pose_sigma
                if "sigma_m" in entry:
                    entry["sigma_m"] = max(float(entry["sigma_m"]), pose_sigma)  # type: ignore[arg-type]  # a float, set above
            heights[image.name] = entry
        self.narrow_heights = heights

    def apply(self, reconstruction: pycolmap.Reconstruction) -> None:
        """Move ``reconstruction`` (in place, scale 1) into this frame; nothing for the mapper's frame."""
        if self.frame != WorldFrame.FLOOR:
            return
        fit = self.estimate.fit  # type: ignore[union-attr]  # FLOOR: estimated
        apply_floor_frame(reconstruction, fit)  # type: ignore[arg-type]  # NoFloor is falsy: a FloorFit here
        logger.info("World: floor frame (%d floor points: %s; RMS %.3g)", fit.num_points, fit.points_by_source,  # type: ignore[union-attr]
                    fit.rms)  # type: ignore[union-attr]

    def to_dict(self) -> dict:
        """narrow_poses.json's ``world`` (summary.json's, as JSON)."""
        return self.summary().to_json()

    def summary(self) -> WorldSummary:
        """summary.json's ``world``."""
        record = WorldSummary(asked=str(self.asked), frame=str(self.frame))
        if self.frame == WorldFrame.FLOOR:
            record.units = "metres" if self.metric else "arbitrary (not metric)"
            record.origin, record.x_axis, record.z_axis = ORIGIN, X_AXIS.format(rig=self.x_rig), Z_AXIS
            record.plane_heights_m = list(self.plane_heights)
        else:
            record.description = ("the mapper's frame after the metric adjustment (arbitrary orientation and origin)"
                                  if self.metric else "the mapper's frame (arbitrary orientation, origin and units)")
        if self.estimate is not None:
            fit = self.estimate.fit
            # FloorFit is truthy: a NoFloor here; NoFloor is falsy: a FloorFit here
            floor = fit.to_dict() if fit else {"found": False, "reason": fit.reason}  # type: ignore[union-attr]
            if fit:
                floor = {"found": True, **{k: floor[k] for k in (
                    "num_points", "points_by_source", "rms", "robust_sigma", "threshold", "num_candidates",
                    "normal_sigma_deg", "camera_height_sigma", "scatter_normal_sigma_deg",
                    "scatter_camera_height_sigma", "group_sigma", "num_groups", "effective_groups", "sigma_basis",
                    "grouped_normal_sigma_deg", "pose_normal_sigma_deg",
                    "camera_height", "prior_angle_deg",
                    "up_prior_source", "marker_residuals", "floor_from_model")}}
                floor["floor_from_mapping"] = floor.pop("floor_from_model")
                floor["refitted_after_narrow_adjustment"] = self.estimate.refitted
                if self.narrow_heights is not None:
                    floor["narrow_camera_heights"] = self.narrow_heights
            floor["matching"] = {"ran": self.estimate.why_matched is not None, "why": self.estimate.why_matched,
                                 "rounds": self.estimate.rounds, "image_pairs": self.estimate.pairs,
                                 "matched_points": self.estimate.matched_points,
                                 "seconds": round(self.estimate.seconds, 3)}
            record.floor = floor
        return record


def first_registered_rig(reconstruction: pycolmap.Reconstruction, rig_names: Sequence[str]) -> str | None:
    registered = {name for name, _ in rig_positions(reconstruction).values()}
    return next((name for name in rig_names if name in registered), None)


def locate_world(reconstruction: pycolmap.Reconstruction, image_dir: Path | None, scale: ScaleSpec | None,
                 rig_names: Sequence[str], options: WorldOptions, *, metric: bool = True) -> WorldResult:
    """Find the frame ``options.frame`` asks for (module docstring) without moving ``reconstruction``:
    :meth:`WorldResult.apply` moves it."""
    if options.frame == WorldFrame.MAPPING:
        return WorldResult(options.frame, WorldFrame.MAPPING, metric=metric)
    x_rig = first_registered_rig(reconstruction, rig_names)
    markers = floor_markers(reconstruction, scale)
    estimate = estimate_floor(reconstruction, image_dir, markers, x_towards=x_rig)
    fit = estimate.fit
    if not fit:
        # FloorFit is truthy: a NoFloor here
        warning = no_floor_warning(fit.reason, len(markers))  # type: ignore[union-attr]
        logger.warning(warning)
        return WorldResult(options.frame, WorldFrame.MAPPING, estimate, metric=metric, warnings=[warning])
    heights = tuple(options.plane_heights)
    if heights and metric:
        # NoFloor is falsy: a FloorFit here
        check_plane_heights(heights, fit.camera_heights)  # type: ignore[union-attr]
    warnings = [f"FLOOR: {w}" for w in fit.warnings]  # type: ignore[union-attr]
    if heights and not metric:
        warnings.append(f"PLANE HEIGHT IGNORED: the result is not metric, so {heights[0]:g} m has no meaning "
                        "here; give a scale.yaml")
        heights = ()
    # NoFloor is falsy: a FloorFit here
    return WorldResult(options.frame, WorldFrame.FLOOR, estimate, fit.origin_rig,  # type: ignore[union-attr]
                       tuple(dict.fromkeys((0.0, *heights))), metric, warnings)


def place_in_world(reconstruction: pycolmap.Reconstruction, image_dir: Path | None, scale: ScaleSpec | None,
                   rig_names: Sequence[str], options: WorldOptions, *, metric: bool = True) -> WorldResult:
    """Move ``reconstruction`` (in place) into the frame ``options.frame`` asks for (module docstring)."""
    world = locate_world(reconstruction, image_dir, scale, rig_names, options, metric=metric)
    world.apply(reconstruction)
    return world


# --- ground maps (narrow_poses.json) ---------------------------------------------------------------------


def _footprint_dict(image: pycolmap.Image, height: float, fp: Footprint | None) -> dict:
    try:
        homography = ground_from_image(image, height).tolist()
    except ValueError:
        homography = None
    entry = {"plane_height_m": float(height), "ground_from_image": homography}
    if fp is None:
        entry.update({"footprint_m": None, "footprint_area_m2": 0.0, "footprint_centre_m": None,
                      "gsd_mm_per_px": None, "gsd_mm_per_px_xy": None, "clipped": None})
        return entry
    entry.update({
        "footprint_m": np.round(fp.polygon, 4).tolist(),
        "footprint_area_m2": fp.area,
        "footprint_centre_m": None if fp.centre is None else fp.centre.tolist(),
        "gsd_mm_per_px": fp.gsd_mm_per_px,
        "gsd_mm_per_px_xy": None if fp.gsd_mm_per_px_xy is None else list(fp.gsd_mm_per_px_xy),
        "clipped": fp.clipped,
    })
    return entry


@dataclass(frozen=True)
class GroundMaps:
    """Per plane height: every narrow image's ground entry; per pair of narrow cameras (``<rig>/narrow``) the
    area both see; the area seen by two or more narrow cameras."""

    heights: tuple[float, ...]
    per_image: dict[str, list[dict]]  # image name -> one entry per height (narrow_poses.json "ground")
    overlaps: dict[tuple[str, str], list[float]]  # (camera a, camera b) -> overlap area (m^2) per height
    seen_twice_m2: list[float]  # area seen by >= 2 narrow cameras, per height

    def overlap(self, image_a: str, image_b: str) -> list[float] | None:
        """Overlap areas per height of the cameras of two images (None for the same camera)."""
        a, b = ImageName.parse(image_a).camera, ImageName.parse(image_b).camera
        if a == b:
            return None
        return self.overlaps.get((min(a, b), max(a, b)), [0.0] * len(self.heights))


def ground_maps(reconstruction: pycolmap.Reconstruction, heights: Sequence[float]) -> GroundMaps:
    """Ground maps of every registered narrow image on each plane ``z = h`` (the model in the floor frame).
    Overlaps and coverage count cameras: each narrow camera by its first registered frame (rigs are static)."""
    images = registered_narrow_images(reconstruction)
    per_image: dict[str, list] = {im.name: [] for im in images}
    first: dict = {}
    for image in images:
        first.setdefault(name_of(image).camera, image.name)
    overlaps: dict[tuple[str, str], list[float]] = {}
    seen_twice = []
    for k, height in enumerate(heights):
        prints = footprints(reconstruction, "narrow", height)
        for image in images:
            per_image[image.name].append(_footprint_dict(image, height, prints.get(image.name)))
        cameras = {camera: prints[name] for camera, name in first.items() if name in prints}
        for overlap in pairwise_overlaps(cameras, pieces=False):
            overlaps.setdefault((overlap.a, overlap.b), [0.0] * len(heights))[k] = overlap.area
        seen_twice.append(coverage(cameras).area_at_least(2))
    return GroundMaps(tuple(float(h) for h in heights), per_image, overlaps, seen_twice)
