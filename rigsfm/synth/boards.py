"""Exact synthetic images for testing calibration: boards and textured planes seen by a hybrid rig.

Rendering is per-pixel ray casting: every (supersampled) pixel centre is undistorted exactly (Newton's
method on OpenCV's distortion, converged to 1e-15, kept in float32: 1e-4 px at a 2 560 px focal), its ray is
intersected with textured planes, and the texture is sampled bilinearly (``cv2.remap``, which itself
quantises texture coordinates to 1/32 texel); supersamples are box-averaged, then slight blur and noise are
added. The ground truth (intrinsics, poses, E^sl) is therefore exact up to texture interpolation.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rigsfm.calibrate.board import BoardSpec

SUPERSAMPLE = 2
# 1 / depth (1 / m) below which a ray misses a plane: a ray this close to parallel would meet it beyond 1000 km, and
# cv2.perspectiveTransform maps it to texture pixel (0, 0) (it zeroes 1 / w for |w| < FLT_EPSILON).
MIN_NEARNESS = np.float32(1e-6)


@dataclass(frozen=True)
class NormalisedPixels:
    """Normalised image coordinates of a camera's supersampled pixel centres (read-only float32): ``xy``
    (h*ss, w*ss, 2) for ``cv2.perspectiveTransform``, and ``x``, ``y`` each contiguous for fast arithmetic;
    ``x_of_column`` (2, w*ss): the least and greatest x of each column, ``y_of_row`` (2, h*ss) the same of y."""

    xy: np.ndarray
    x: np.ndarray
    y: np.ndarray
    x_of_column: np.ndarray
    y_of_row: np.ndarray

    def window(self, x_range: tuple[float, float], y_range: tuple[float, float]) -> tuple[slice, slice] | None:
        """The rows and columns (slices) outside which no pixel's (x, y) lies in ``x_range`` x ``y_range``: a
        column whose x all lie outside ``x_range`` holds none, nor does such a row for y. None: no pixel does."""
        columns = np.flatnonzero((self.x_of_column[1] >= x_range[0]) & (self.x_of_column[0] <= x_range[1]))
        rows = np.flatnonzero((self.y_of_row[1] >= y_range[0]) & (self.y_of_row[0] <= y_range[1]))
        if len(columns) == 0 or len(rows) == 0:
            return None
        return slice(rows[0], rows[-1] + 1), slice(columns[0], columns[-1] + 1)


def _newton_undistort(u: np.ndarray, v: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undistorted normalised (x, y) of distorted normalised (u, v) under OpenCV's (k1, k2, p1, p2, k3), by
    Newton's method from (u, v) until its steps fall below 1e-15, and where it converged (steps < 1e-12)."""
    k1, k2, p1, p2, k3 = (*np.ravel(dist), 0.0, 0.0, 0.0, 0.0, 0.0)[:5]
    x, y = u.copy(), v.copy()
    step = np.full(u.shape, np.inf)
    for _ in range(30):
        x2, y2, xy = x * x, y * y, x * y
        r2 = x2 + y2
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        radial_r2 = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # 2 d(radial)/d(r2)
        ex = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2) - u
        ey = y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy - v
        a = radial + x2 * radial_r2 + 2 * p1 * y + 6 * p2 * x  # Jacobian [[a, b], [b, d]]
        b = xy * radial_r2 + 2 * p1 * x + 2 * p2 * y
        d = radial + y2 * radial_r2 + 6 * p1 * y + 2 * p2 * x
        det = a * d - b * b
        dx, dy = (d * ex - b * ey) / det, (a * ey - b * ex) / det
        x -= dx
        y -= dy
        step = np.maximum(np.abs(dx), np.abs(dy))
        if not step.max() >= 1e-15:  # also stops on NaN
            break
    return x, y, step < 1e-12


def _undistort(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """Normalised coordinates (N x 2) of OpenCV ``pixels`` (N x 2), by :func:`_newton_undistort`. The board
    cameras' supersamples: equal to ``cv2.undistortPoints`` (100 iterations, eps 1e-14) to rounding, and
    several times faster. A ValueError where it does not converge (pixels beyond the
    distortion's monotonic range: no ray to render)."""
    if len(dist) > 5:
        raise ValueError(f"the board renderer takes OpenCV distortions (k1, k2, p1, p2, k3), not {len(dist)} terms")
    result = np.empty(pixels.shape, np.float64)
    for start in range(0, len(pixels), chunk):
        v = (pixels[start:start + chunk, 1] - K[1, 2]) / K[1, 1]
        u = (pixels[start:start + chunk, 0] - K[0, 2] - K[0, 1] * v) / K[0, 0]
        x, y, converged = _newton_undistort(u, v, dist)
        if not converged.all():
            raise ValueError(f"distortion {np.ravel(dist).tolist()} cannot be undone at {np.sum(~converged)} pixels "
                             "(beyond its monotonic range): no camera to render")
        result[start:start + chunk, 0], result[start:start + chunk, 1] = x, y
    return result


@functools.lru_cache(maxsize=4)
def _normalised_pixels(key: bytes, K: tuple, dist: tuple, size: tuple[int, int]) -> NormalisedPixels:
    """Cached per camera: undistorting a 960x720 camera's 2.8 M supersamples takes ~0.5-0.9 s, and the board
    benchmarks and tests render many boards with a few cameras."""
    w, h = size
    u = (np.arange(w * SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    v = (np.arange(h * SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    uu, vv = np.meshgrid(u, v)
    pix = np.stack([uu, vv], -1).reshape(-1, 2)
    xy = _undistort(pix, np.array(K).reshape(3, 3), np.array(dist)).reshape(uu.shape + (2,)).astype(np.float32)
    x, y = np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])
    pixels = NormalisedPixels(xy, x, y, np.stack([x.min(axis=0), x.max(axis=0)]),
                              np.stack([y.min(axis=1), y.max(axis=1)]))
    for array in (pixels.xy, pixels.x, pixels.y, pixels.x_of_column, pixels.y_of_row):
        array.flags.writeable = False
    return pixels


@dataclass
class SynthCamera:
    """An OpenCV camera: K (pixel centres at integers), distortion (k1, k2, p1, p2, k3), size (w, h)."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]

    def normalised_pixels(self) -> NormalisedPixels:
        """Normalised coordinates (x, y) of the supersampled pixel centres: the rays (x, y, 1)."""
        K, dist = np.asarray(self.K, np.float64), np.asarray(self.dist, np.float64)
        return _normalised_pixels(K.tobytes() + dist.tobytes(), tuple(K.ravel()), tuple(dist.ravel()),
                                  tuple(self.size))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        pts, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return pts.reshape(-1, 2)


@dataclass
class TexturedPlane:
    """A plane z = 0 in its own frame, placed by ``world_from_plane`` (R, t); texture pixel = metres / texel."""

    rotation: np.ndarray
    translation: np.ndarray
    texture: np.ndarray  # uint8 gray
    texel: float  # metres per texture pixel
    origin_px: tuple[float, float] = (0.0, 0.0)  # texture pixel (area convention) of the plane origin
    background: float = 128.0


def _plane_window(camera: SynthCamera, pixels: NormalisedPixels, H: np.ndarray,
                  plane: TexturedPlane) -> tuple[slice, slice] | None:
    """Rows and columns of the supersampled image outside which ``plane``'s texture shows in no pixel (None:
    in none at all); the whole image where the plane reaches behind the camera. With the texture's rectangle
    wholly in front, what it covers in normalised coordinates is the convex hull of its corners' images,
    inside their bounding box (widened by 4 pixels for float32's rounding of the texture coordinates)."""
    h, w = plane.texture.shape
    corners = (np.array([[0, 0], [w, 0], [w, h], [0, h]], float) - plane.origin_px) * plane.texel
    rays = np.column_stack([corners, np.ones(4)]) @ H.T  # (x, y, 1) * depth
    if not np.all(rays[:, 2] > 0):
        return slice(None), slice(None)
    xy = rays[:, :2] / rays[:, 2:]
    margin = 4.0 / min(camera.K[0, 0], camera.K[1, 1])
    return pixels.window((xy[:, 0].min() - margin, xy[:, 0].max() + margin),
                         (xy[:, 1].min() - margin, xy[:, 1].max() + margin))


def render(camera: SynthCamera, cam_from_world: tuple[np.ndarray, np.ndarray], planes: list[TexturedPlane],
           rng: np.random.Generator, blur: float = 0.6, noise: float = 1.5, background: float = 110.0) -> np.ndarray:
    """Ray-cast ``planes`` into ``camera``; nearest plane in front wins; returns a uint8 image. Each plane is
    cast only over the window of pixels its texture can reach (:func:`_plane_window`): every step is per pixel,
    so the image is the one casting every pixel gives."""
    R, t = cam_from_world
    pixels = camera.normalised_pixels()
    shape = pixels.x.shape
    image = np.full(shape, background, np.float32)
    nearness = np.zeros(shape, np.float32)  # 1 / depth of the nearest plane hit so far (0: none)
    for plane in planes:
        # plane points in the camera: cam_R_plane [X, Y, 0] + cam_t_plane
        cR = R @ plane.rotation
        ct = R @ plane.translation + t
        H = np.column_stack([cR[:, 0], cR[:, 1], ct])  # normalised ray (x, y, 1) ~ H [X, Y, 1]
        window = _plane_window(camera, pixels, H, plane)
        if window is None:
            continue
        a = np.linalg.inv(H)
        texture_from_ray = np.array([[1.0 / plane.texel, 0.0, plane.origin_px[0] - 0.5],
                                     [0.0, 1.0 / plane.texel, plane.origin_px[1] - 0.5], [0.0, 0.0, 1.0]]) @ a
        maps = cv2.perspectiveTransform(pixels.xy[window], texture_from_ray)  # texture pixel of every ray
        # 1 / depth: the ray (x, y, 1) meets the plane at depth 1 / (a[2] . (x, y, 1)), in front if positive
        near = np.float32(a[2, 0]) * pixels.x[window] + np.float32(a[2, 1]) * pixels.y[window] + np.float32(a[2, 2])
        h, w = plane.texture.shape
        inside = cv2.inRange(maps, (-0.5, -0.5), (w - 0.5, h - 0.5)) > 0
        visible = (near > np.maximum(nearness[window], MIN_NEARNESS)) & inside
        # stubs: map2 None
        sampled = cv2.remap(plane.texture, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # type: ignore[call-overload]
        np.copyto(image[window], sampled, where=visible)
        np.copyto(nearness[window], near, where=visible)
    w, h = camera.size
    image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)  # type: ignore[assignment]  # an image array
    if blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur)  # type: ignore[assignment]  # an image array
    image = image + rng.normal(0.0, noise, image.shape)  # type: ignore[assignment]
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def board_plane(spec: BoardSpec, px_per_square: int = 120) -> TexturedPlane:
    """The board as a textured plane in its own frame (world = board), with a white quiet zone."""
    margin = px_per_square
    if spec.type == "charuco":
        cols, rows = spec.squares  # type: ignore[misc]  # ChArUco: squares set
        size = (cols * px_per_square + 2 * margin, rows * px_per_square + 2 * margin)
        texture = spec.charuco_board().generateImage(size, marginSize=margin, borderBits=1)
        origin = (float(margin), float(margin))
    else:
        cols, rows = spec.inner_corners[0] + 1, spec.inner_corners[1] + 1  # type: ignore[index]  # chessboard: set
        cells = np.indices((rows, cols)).sum(0) % 2 == 0
        board = np.where(cells, 0, 255).astype(np.uint8).repeat(px_per_square, 0).repeat(px_per_square, 1)
        texture = cv2.copyMakeBorder(board, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
        origin = (float(margin + px_per_square), float(margin + px_per_square))  # first inner corner
    return TexturedPlane(np.eye(3), np.zeros(3), texture, spec.square / px_per_square, origin)


def noise_texture(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """Multi-scale random texture with blobs: plenty of SIFT features at every scale."""
    w, h = size
    acc = np.zeros((h, w), np.float32)
    for cell in (64, 24, 8, 3):
        small = rng.random((h // cell + 2, w // cell + 2)).astype(np.float32)
        acc += cv2.resize(small, (w + 2 * cell, h + 2 * cell), interpolation=cv2.INTER_CUBIC)[cell:cell + h, cell:cell + w]
    acc = cv2.normalize(acc, None, 0, 255, cv2.NORM_MINMAX)  # type: ignore[call-overload]  # stubs: dst None
    for _ in range(w * h // 4000):
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(acc, centre, int(rng.integers(3, 25)), float(rng.integers(0, 256)), -1, cv2.LINE_AA)
    return acc.astype(np.uint8)


def rotation_xyz_deg(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.radians([rx, 0, 0]))[0] @ cv2.Rodrigues(np.radians([0, ry, 0]))[0] @ \
        cv2.Rodrigues(np.radians([0, 0, rz]))[0]


@dataclass
class HybridRig:
    wide: SynthCamera
    narrow: SynthCamera
    R: np.ndarray  # narrow_from_wide rotation
    t: np.ndarray  # narrow_from_wide translation (metres)


def default_hybrid_rig(size: tuple[int, int] = (960, 720), focal_wide: float = 640.0, ratio: float = 4.0) -> HybridRig:
    w, h = size
    K_w = np.array([[focal_wide, 0, w / 2 - 3.2], [0, focal_wide * 1.001, h / 2 + 4.7], [0, 0, 1]])
    K_n = np.array([[focal_wide * ratio, 0, w / 2 + 5.1], [0, focal_wide * ratio * 0.9995, h / 2 - 2.3], [0, 0, 1]])
    return HybridRig(
        wide=SynthCamera(K_w, np.array([-0.12, 0.035, 0.0006, -0.0004, 0.0]), size),
        narrow=SynthCamera(K_n, np.array([-0.05, 0.1, 0.0, 0.0, 0.0]), size),
        R=rotation_xyz_deg(0.8, -1.5, 0.6),
        t=np.array([-0.12, 0.004, 0.003]),
    )


def board_views(rng: np.random.Generator, n_stereo: int, n_wide_only: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``wide_from_board`` poses: ``n_stereo`` near the optical axis (the narrow camera sees part of the
    board) then ``n_wide_only`` towards the edges of the wide image."""
    poses = []
    for i in range(n_stereo + n_wide_only):
        stereo = i < n_stereo
        tilt = 55 if stereo else 35
        R = rotation_xyz_deg(rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt), rng.uniform(-20, 20))
        z = rng.uniform(0.75, 1.3) if stereo else rng.uniform(0.5, 0.8)
        lateral = 0.15 if stereo else 0.6
        centre = np.array([rng.uniform(-lateral, lateral) * z, rng.uniform(-lateral, lateral) * z * 0.75, z])
        if not stereo and abs(centre[0]) < 0.2 * z:
            centre[0] = np.sign(centre[0] + 1e-9) * 0.3 * z
        poses.append((R, centre))
    return poses


def _maybe_visible(camera: SynthCamera, cam_from_plane, plane: TexturedPlane) -> bool:
    """False only if the whole textured plane is surely outside the view (all corners beyond one border)."""
    h, w = plane.texture.shape
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float) - plane.origin_px
    pts = np.column_stack([corners * plane.texel, np.zeros(4)]) @ cam_from_plane[0].T + cam_from_plane[1]
    if np.any(pts[:, 2] <= 0):
        return True
    uv = pts[:, :2] / pts[:, 2:] @ camera.K[:2, :2].T + camera.K[:2, 2]
    margin = 0.2 * max(camera.size)  # generous: distortion moves points near the borders
    return not (np.all(uv[:, 0] < -margin) or np.all(uv[:, 1] < -margin) or
                np.all(uv[:, 0] > camera.size[0] + margin) or np.all(uv[:, 1] > camera.size[1] + margin))


def write_board_dataset(root: Path, rig_name: str, spec: BoardSpec, rig: HybridRig, poses, seed: int = 0) -> list[str]:
    """Render ``poses`` (board centre poses in the wide frame) into ``root/<rig>/{wide,narrow}/NNN.png``."""
    rng = np.random.default_rng(seed)
    plane = board_plane(spec)
    th, tw = plane.texture.shape
    centre_board = np.array([(tw / 2 - plane.origin_px[0]) * plane.texel, (th / 2 - plane.origin_px[1]) * plane.texel, 0])
    names = []
    for sensor in ("wide", "narrow"):
        (root / rig_name / sensor).mkdir(parents=True, exist_ok=True)
    for index, (R, centre) in enumerate(poses):
        t = centre - R @ centre_board  # wide_from_board translation so the board centre lands at ``centre``
        name = f"{index:03d}.png"
        wide = render(rig.wide, (R, t), [plane], rng)
        narrow_pose = (rig.R @ R, rig.R @ t + rig.t)
        narrow = render(rig.narrow, narrow_pose, [plane] if _maybe_visible(rig.narrow, narrow_pose, plane) else [], rng)
        cv2.imwrite(str(root / rig_name / "wide" / name), wide)
        cv2.imwrite(str(root / rig_name / "narrow" / name), narrow)
        names.append(name)
    return names


def scene_planes(rng: np.random.Generator) -> list[TexturedPlane]:
    """Two textured planes facing the rig (wide frame = world): a tilted wall at ~4 m and a panel at ~2 m."""
    far = TexturedPlane(rotation_xyz_deg(10, -15, 0), np.array([-3.0, -2.2, 4.0]), noise_texture(rng, (1500, 1100)), 0.004)
    near = TexturedPlane(rotation_xyz_deg(-5, 20, 3), np.array([-0.6, -0.1, 2.0]), noise_texture(rng, (900, 500)), 0.0015)
    return [far, near]


def write_scene_dataset(root: Path, rig_name: str, rig: HybridRig, n_frames: int = 2, seed: int = 1) -> None:
    """Render the two-plane textured scene from ``n_frames`` rig poses into ``root/<rig>/{wide,narrow}``."""
    rng = np.random.default_rng(seed)
    planes = scene_planes(rng)
    for sensor in ("wide", "narrow"):
        (root / rig_name / sensor).mkdir(parents=True, exist_ok=True)
    for index in range(n_frames):
        Rw = rotation_xyz_deg(rng.uniform(-3, 3), rng.uniform(-4, 4), rng.uniform(-2, 2))
        tw = rng.uniform(-0.1, 0.1, 3)
        cv2.imwrite(str(root / rig_name / "wide" / f"{index:03d}.png"), render(rig.wide, (Rw, tw), planes, rng))
        cv2.imwrite(str(root / rig_name / "narrow" / f"{index:03d}.png"),
                    render(rig.narrow, (rig.R @ Rw, rig.R @ tw + rig.t), planes, rng))
