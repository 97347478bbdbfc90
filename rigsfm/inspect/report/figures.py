"""Figures for report.html in the one chart style (rigsfm.core.charts): OpenCV images (epipolar check, embedded
as JPEG) and inline SVG maps (the network seen from above).

Pixel conventions: pycolmap cameras use COLMAP pixels (first pixel centre at (0.5, 0.5)); OpenCV drawing
uses pixel indices (first pixel centre at (0, 0)), so every point is converted with
``opencv_from_colmap_pixels`` before it is drawn.
"""

from __future__ import annotations

import html
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core import charts
from rigsfm.core.conventions import opencv_from_colmap_pixels
from rigsfm.core.geometry import project
from rigsfm.core.image_files import read_image as read_pixels
from rigsfm.core.names import name_of

COLOURS_BGR = [charts.bgr(colour) for colour in charts.SERIES]
WIDE_SVG, NARROW_SVG = charts.hex_colour("wide"), charts.hex_colour("narrow")
JPEG_QUALITY = 85  # the epipolar panels are photographs with thin lines: far smaller than PNG, lines still crisp


def pick_points(image_gray: np.ndarray, camera: pycolmap.Camera, count: int = 8) -> np.ndarray:
    """Strongest corners of a narrow image (COLMAP pixels), topped up from a grid where it is homogeneous."""
    mask = np.zeros(image_gray.shape, np.uint8)
    h, w = image_gray.shape
    mask[int(0.06 * h):int(0.94 * h), int(0.06 * w):int(0.94 * w)] = 255  # not on the border
    corners = cv2.goodFeaturesToTrack(image_gray, maxCorners=count, qualityLevel=0.05,
                                      minDistance=0.15 * min(image_gray.shape), mask=mask)
    points = [] if corners is None else [c.ravel() + 0.5 for c in corners]
    grid = [(camera.width * x, camera.height * y) for y in (0.3, 0.5, 0.7) for x in (0.25, 0.5, 0.75)]
    for g in grid:
        if len(points) >= count:
            break
        if all(np.hypot(*(np.asarray(g) - p)) > 0.12 * camera.width for p in points):
            points.append(np.asarray(g, dtype=np.float64))
    return np.array(points[:count], dtype=np.float64)


def epipolar_curve(camera_i: pycolmap.Camera, camera_j: pycolmap.Camera, j_from_i: pycolmap.Rigid3d,
                   pixel_i: np.ndarray, num: int = 200) -> np.ndarray:
    """The epipolar line of a pixel of i as drawn in the raw (distorted) image j: the ray's projections."""
    ray = np.append(np.asarray(camera_i.cam_from_img(pixel_i.reshape(1, 2))).ravel(), 1.0)
    distance = max(float(np.linalg.norm(j_from_i.translation)), 1e-6)
    depths = np.geomspace(0.05 * distance, 1e4 * distance, num)
    in_j = np.asarray(j_from_i * (ray[None, :] * depths[:, None]))
    # a little beyond the border so the line reaches it; points the distortion folds back are dropped
    xy, seen = project(camera_j, in_j, margin_px=-0.2 * max(camera_j.width, camera_j.height))
    return xy[seen]


def _offset(curve: np.ndarray, distance: float) -> np.ndarray:
    tangent = np.gradient(curve, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return curve + distance * np.column_stack([-tangent[:, 1], tangent[:, 0]])


def _to_cv(points: np.ndarray, scale: float) -> np.ndarray:
    return np.round(opencv_from_colmap_pixels(points) * scale * 16).astype(np.int32)  # 4 fractional bits


def epipolar_figure(image_i: np.ndarray, image_j: np.ndarray, camera_i: pycolmap.Camera,
                    camera_j: pycolmap.Camera, j_from_i: pycolmap.Rigid3d, band_px: float | None,
                    width: int = 560) -> np.ndarray:
    """Side by side: points in narrow image i, their epipolar lines (and 95 % band) in narrow image j."""
    gray_i = image_i if image_i.ndim == 2 else cv2.cvtColor(image_i, cv2.COLOR_BGR2GRAY)
    points = pick_points(gray_i, camera_i)
    panels = []
    for image, camera in ((image_i, camera_i), (image_j, camera_j)):
        scale = width / camera.width
        panel = cv2.resize(image, (width, int(round(camera.height * scale))), interpolation=cv2.INTER_AREA)
        panels.append((panel if panel.ndim == 3 else cv2.cvtColor(panel, cv2.COLOR_GRAY2BGR), scale))
    (left, scale_i), (right, scale_j) = panels
    overlay = right.copy()
    for k, point in enumerate(points):
        colour = COLOURS_BGR[k % len(COLOURS_BGR)]
        cv2.circle(left, tuple(_to_cv(point, scale_i)), 7 * 16, colour, 2, cv2.LINE_AA, shift=4)
        cv2.putText(left, str(k + 1), tuple(int(v) for v in opencv_from_colmap_pixels(point) * scale_i + 9),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
        curve = epipolar_curve(camera_i, camera_j, j_from_i, point)
        if len(curve) < 2:
            continue
        if band_px is not None and np.isfinite(band_px):
            polygon = np.vstack([_offset(curve, band_px), _offset(curve, -band_px)[::-1]])
            cv2.fillPoly(overlay, [_to_cv(polygon, scale_j)], colour, cv2.LINE_AA, shift=4)
        cv2.polylines(right, [_to_cv(curve, scale_j)], False, colour, 1, cv2.LINE_AA, shift=4)
    right = cv2.addWeighted(overlay, 0.25, right, 0.75, 0.0)
    for k, point in enumerate(points):  # re-draw the lines over the translucent band
        curve = epipolar_curve(camera_i, camera_j, j_from_i, point)
        if len(curve) >= 2:
            cv2.polylines(right, [_to_cv(curve, scale_j)], False, COLOURS_BGR[k % len(COLOURS_BGR)], 1,
                          cv2.LINE_AA, shift=4)
    height = max(left.shape[0], right.shape[0])
    canvas = np.full((height, left.shape[1] + right.shape[1] + 8, 3), 255, np.uint8)
    canvas[:left.shape[0], :left.shape[1]] = left
    canvas[:right.shape[0], left.shape[1] + 8:] = right
    return canvas


def read_image(path: Path) -> np.ndarray | None:
    return read_pixels(path, cv2.IMREAD_COLOR)  # as stored: the model's keypoints are in that frame


def ground_frame(reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(origin, 3x3 rows = [east, north, up]): the plane of the points and cameras seen from above."""
    centres = np.array([im.projection_center() for im in reconstruction.images.values() if im.has_pose])
    xyz = np.array([p.xyz for p in reconstruction.points3D.values()]) if reconstruction.num_points3D() else centres
    cloud = np.vstack([xyz, centres])
    origin = np.median(cloud, axis=0)
    _, _, vt = np.linalg.svd(cloud - origin, full_matrices=False)
    up = vt[2]
    image_up = np.mean([-(im.cam_from_world().rotation.matrix()[1]) for im in reconstruction.images.values()
                        if im.has_pose], axis=0)  # -y of the cameras points up
    if np.dot(up, image_up) < 0:
        up = -up
    east = vt[0] - np.dot(vt[0], up) * up
    east /= np.linalg.norm(east)
    return origin, np.array([east, np.cross(up, east), up])


def topdown_svg(reconstruction: pycolmap.Reconstruction, size: int = 620, max_points: int = 4000,
                units: str = "m", floor_frame: bool = False) -> str:
    """Top view of the network: points, wide and narrow cameras with their viewing directions, axes. In the floor
    frame it is drawn in the floor's own x and y, as the floor map is; otherwise in the points' best-fit plane."""
    origin, axes = (np.zeros(3), np.eye(3)) if floor_frame else ground_frame(reconstruction)
    images = [im for im in reconstruction.images.values() if im.has_pose]
    xyz = np.array([p.xyz for p in reconstruction.points3D.values()]) if reconstruction.num_points3D() else np.zeros((0, 3))
    if len(xyz) > max_points:
        xyz = xyz[np.random.default_rng(0).choice(len(xyz), max_points, replace=False)]
    points2 = (xyz - origin) @ axes[:2].T
    centres2 = (np.array([im.projection_center() for im in images]) - origin) @ axes[:2].T
    extent_pts = points2 if len(points2) else centres2
    lo = np.minimum(np.percentile(extent_pts, 1, axis=0), centres2.min(axis=0))
    hi = np.maximum(np.percentile(extent_pts, 99, axis=0), centres2.max(axis=0))
    span = float(max(hi - lo)) * 1.1 or 1.0
    mid = (lo + hi) / 2
    pad = 40
    scale = (size - 2 * pad) / span

    def to_svg(p: np.ndarray) -> tuple[float, float]:
        return pad + (p[0] - mid[0] + span / 2) * scale, size - pad - (p[1] - mid[1] + span / 2) * scale

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" role="img" '
             f'style="background:#fff;border:1px solid #ccc">']
    step = charts.nice_ticks(span, 6)[1]
    for k in np.arange(np.ceil((mid[0] - span / 2) / step), np.floor((mid[0] + span / 2) / step) + 1):
        x, _ = to_svg(np.array([k * step, 0.0]))
        parts.append(f'<line x1="{x:.1f}" y1="{pad}" x2="{x:.1f}" y2="{size - pad}" stroke="#eee"/>'
                     f'<text x="{x:.1f}" y="{size - pad + 14}" font-size="10" text-anchor="middle">{k * step:g}</text>')
    for k in np.arange(np.ceil((mid[1] - span / 2) / step), np.floor((mid[1] + span / 2) / step) + 1):
        _, y = to_svg(np.array([0.0, k * step]))
        parts.append(f'<line x1="{pad}" y1="{y:.1f}" x2="{size - pad}" y2="{y:.1f}" stroke="#eee"/>'
                     f'<text x="{pad - 4}" y="{y + 3:.1f}" font-size="10" text-anchor="end">{k * step:g}</text>')
    parts.append("".join(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="0.8" fill="#888"/>'
                         for x, y in (to_svg(p) for p in points2)))
    for image, centre in zip(images, centres2):
        narrow = name_of(image).is_narrow
        colour = NARROW_SVG if narrow else WIDE_SVG
        view = image.cam_from_world().rotation.matrix()[2] @ axes[:2].T
        view = view / max(np.linalg.norm(view), 1e-9) * (0.12 if narrow else 0.07) * span
        (x0, y0), (x1, y1) = to_svg(centre), to_svg(centre + view)
        # a rig's two centres are centimetres apart: the wide one is a ring round the narrow one's dot
        marker = (f'r="3" fill="{colour}"' if narrow else f'r="6.5" fill="none" stroke="{colour}" stroke-width="2"')
        parts.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" stroke="{colour}" '
                     f'stroke-width="2"/><circle class="{"narrow" if narrow else "wide"}" cx="{x0:.1f}" '
                     f'cy="{y0:.1f}" {marker}/>')
        if not narrow:
            parts.append(f'<text x="{x0 + 6:.1f}" y="{y0 - 6:.1f}" font-size="11">'
                         f'{html.escape(name_of(image).rig)}</text>')
    frame = ("the floor frame's x (right) and y (up), as in the floor map" if floor_frame else
             "seen from above the points' best-fit plane (not the floor map's axes)")
    parts.append(f'<text x="{pad}" y="14" font-size="11">grid {step:g} {units}; '
                 f'<tspan fill="{WIDE_SVG}">wide (ring)</tspan>, <tspan fill="{NARROW_SVG}">narrow (dot)</tspan> '
                 f'cameras with viewing directions; grey: sparse points</text>'
                 f'<text class="frame" x="{pad}" y="28" font-size="11">{frame}</text></svg>')
    return "".join(parts)


STEREO_SVG = charts.hex_colour(charts.SERIES[1])  # areas seen by two or more narrow cameras


def _svg_path(points: np.ndarray, to_svg) -> str:
    return "M" + " L".join("{:.1f},{:.1f}".format(*to_svg(p)) for p in points) + " Z"


def floor_map_svg(narrow: dict, reconstruction: pycolmap.Reconstruction, size: int = 620) -> str | None:
    """The floor seen from above, to scale (floor frame, metres): rigs, every narrow camera's footprint and the
    areas seen by two or more narrow cameras, with a metre grid. None when narrow_poses.json has no ground
    maps (the result is not in the floor frame)."""
    from rigsfm.core.ground import coverage

    prints: dict = {}
    centres: dict = {}
    for entry in narrow.get("narrow", []):
        ground = entry.get("ground") or []
        floor = next((g for g in ground if g.get("plane_height_m") == 0.0 and g.get("footprint_m")), None)
        camera = entry["name"].rsplit("/", 1)[0]
        if floor is not None and camera not in prints:
            prints[camera] = np.asarray(floor["footprint_m"], dtype=np.float64)
    if not prints:
        return None
    for image in reconstruction.images.values():
        if image.has_pose and not name_of(image).is_narrow:
            centres.setdefault(name_of(image).rig, np.asarray(image.projection_center())[:2])
    twice = coverage(prints, cell=0.05).outlines(2)
    everything = np.vstack([*prints.values(), *(c[None] for c in centres.values())])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    span = float(max(hi - lo)) * 1.08 or 1.0
    mid = (lo + hi) / 2
    pad = 40
    scale = (size - 2 * pad) / span

    def to_svg(p) -> tuple[float, float]:
        return pad + (p[0] - mid[0] + span / 2) * scale, size - pad - (p[1] - mid[1] + span / 2) * scale

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" role="img" '
             f'style="background:#fff;border:1px solid #ccc">']
    step = max(1.0, charts.nice_ticks(span, 6)[1])  # whole metres
    if step > 1.0 and span < 120.0:  # and light lines every metre
        for k in np.arange(np.ceil(mid[0] - span / 2), np.floor(mid[0] + span / 2) + 1):
            x, _ = to_svg((k, 0.0))
            parts.append(f'<line x1="{x:.1f}" y1="{pad}" x2="{x:.1f}" y2="{size - pad}" stroke="#f4f4f4"/>')
        for k in np.arange(np.ceil(mid[1] - span / 2), np.floor(mid[1] + span / 2) + 1):
            _, y = to_svg((0.0, k))
            parts.append(f'<line x1="{pad}" y1="{y:.1f}" x2="{size - pad}" y2="{y:.1f}" stroke="#f4f4f4"/>')
    for k in np.arange(np.ceil((mid[0] - span / 2) / step), np.floor((mid[0] + span / 2) / step) + 1):
        x, _ = to_svg((k * step, 0.0))
        parts.append(f'<line x1="{x:.1f}" y1="{pad}" x2="{x:.1f}" y2="{size - pad}" stroke="#e4e4e4"/>'
                     f'<text x="{x:.1f}" y="{size - pad + 14}" font-size="10" text-anchor="middle">{k * step:g}</text>')
    for k in np.arange(np.ceil((mid[1] - span / 2) / step), np.floor((mid[1] + span / 2) / step) + 1):
        _, y = to_svg((0.0, k * step))
        parts.append(f'<line x1="{pad}" y1="{y:.1f}" x2="{size - pad}" y2="{y:.1f}" stroke="#e4e4e4"/>'
                     f'<text x="{pad - 4}" y="{y + 3:.1f}" font-size="10" text-anchor="end">{k * step:g}</text>')
    for camera, polygon in prints.items():
        parts.append(f'<path d="{_svg_path(polygon, to_svg)}" fill="{NARROW_SVG}" fill-opacity="0.08" '
                     f'stroke="{NARROW_SVG}" stroke-width="1"><title>{html.escape(camera)}</title></path>')
    for outline in twice:
        parts.append(f'<path d="{_svg_path(outline, to_svg)}" fill="{STEREO_SVG}" fill-opacity="0.35" '
                     f'stroke="{STEREO_SVG}" stroke-width="1"/>')
    for rig, centre in sorted(centres.items()):
        x, y = to_svg(centre)
        parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="4" fill="{WIDE_SVG}"/>'
                     f'<text x="{x + 6:.1f}" y="{y - 6:.1f}" font-size="11">{html.escape(rig)}</text>')
    (x0, y0), (x1, y1) = to_svg((0.0, 0.0)), to_svg((step, 0.0))
    parts.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" stroke="#333" stroke-width="2"/>'
                 f'<circle cx="{x0:.1f}" cy="{y0:.1f}" r="2.5" fill="#333"/>'
                 f'<text x="{x1 + 3:.1f}" y="{y1 + 4:.1f}" font-size="10">x</text>')
    parts.append(f'<text x="{pad}" y="16" font-size="11">floor (z = 0), grid 1 m, labels every {step:g} m; '
                 f'<tspan fill="{WIDE_SVG}">rigs</tspan>, <tspan fill="{NARROW_SVG}">narrow footprints</tspan>, '
                 f'<tspan fill="{STEREO_SVG}">seen by 2+ narrow cameras</tspan></text></svg>')
    return "".join(parts)
