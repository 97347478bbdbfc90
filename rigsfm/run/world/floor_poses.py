"""The floor's tilt error, and the cameras' heights above it, from the poses' own covariance: the adjustment's joint
covariance of the rig poses carried through the floor points' triangulation (floor matches and sparse points) into the
plane (the floor points of one image pair share that pair's pose error, and neighbouring pairs share cameras: a
network's errors are correlated, which the points' residuals cannot show, benchmarks/README.md)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from rigsfm.core.geometry import skew, triangulate_views
from rigsfm.run.adjustment.result import JointCovariance

if TYPE_CHECKING:  # floor matching imports OpenCV: a floor of sparse points has no matches
    from rigsfm.run.world.floor_matching import FloorMatches

STEP = 1e-6  # central differences: radians for the rotation, model units for the translation


def _rays(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    return np.asarray(camera.cam_from_img(np.asarray(xy, np.float64).reshape(-1, 2)), np.float64)


def _pose(rotation: np.ndarray, translation: np.ndarray, w: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """``rig_from_world`` moved by the covariance's tangent ``[w, dt]``: R' = Exp(w) R, t' = t + dt."""
    angle = float(np.linalg.norm(w))
    exp = np.eye(3) if angle == 0 else pycolmap.Rotation3d(w).matrix()
    return np.c_[exp @ rotation, translation + dt]


def _reference_sensor(reconstruction: pycolmap.Reconstruction, image: pycolmap.Image) -> bool:
    """Whether ``image``'s pose is its frame's (its rig's reference sensor: a wide image)."""
    return np.array_equal(image.cam_from_world().matrix(),
                          reconstruction.frame(image.frame_id).rig_from_world.matrix())  # type: ignore[union-attr]  # registered


def floor_views(reconstruction: pycolmap.Reconstruction, matches: FloorMatches | None,
                sparse_ids: Sequence[int] | np.ndarray, frames: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The floor points' observations in reference-sensor images of ``frames``, grouped by how many each has:
    per group (frame indices into ``frames``, P x n; normalised rays, P x n x 2). Floor matches: their two pixels;
    sparse points (``sparse_ids``): every observation of their track in such an image, where two or more."""
    images = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    index = {f: k for k, f in enumerate(frames)}
    by_count: dict[int, tuple[list, list]] = {}
    for m in matches.matches if matches is not None else ():
        a, b = images.get(m.image_i), images.get(m.image_j)
        if a is None or b is None or not len(m.xy_i) or a.frame_id not in index or b.frame_id not in index \
                or not (_reference_sensor(reconstruction, a) and _reference_sensor(reconstruction, b)):
            continue
        views, rays = by_count.setdefault(2, ([], []))
        views.append(np.tile([index[a.frame_id], index[b.frame_id]], (len(m.xy_i), 1)))
        rays.append(np.stack([_rays(a.camera, m.xy_i), _rays(b.camera, m.xy_j)], axis=1))  # type: ignore[arg-type]
    reference = {image.image_id: image for image in images.values()
                 if image.frame_id in index and _reference_sensor(reconstruction, image)}
    points3D = reconstruction.points3D
    for point_id in sparse_ids:
        if int(point_id) not in points3D:  # a fit kept from the model before the second adjustment
            continue
        seen: dict[int, tuple] = {}  # frame -> (image, pixel): one observation per frame (a track holds one per image)
        for element in reconstruction.point3D(int(point_id)).track.elements:
            image = reference.get(element.image_id)
            if image is not None:
                seen.setdefault(image.frame_id, (image, image.points2D[element.point2D_idx].xy))
        if len(seen) >= 2:
            views, rays = by_count.setdefault(len(seen), ([], []))
            views.append(np.array([[index[f] for f in seen]]))
            rays.append(np.stack([_rays(image.camera, xy[None]) for image, xy in seen.values()], axis=1))
    return [(np.vstack(views), np.vstack(rays)) for views, rays in by_count.values()]


def pose_floor_covariance(reconstruction: pycolmap.Reconstruction, matches: FloorMatches | None, normal: np.ndarray,
                          offset: float, threshold: float, covariance: JointCovariance,
                          sparse_ids: Sequence[int] | np.ndarray = ()) -> tuple[np.ndarray, dict[str, float]] | None:
    """From the poses' covariance alone: the 2x2 covariance (radians^2) of the floor's tilt relative to the cameras'
    mean orientation (the error of the normal seen from the cameras, in-plane axes), and each posed image's height
    above the floor's 1 sigma (model units), the camera and the floor moved together by the same poses. Each floor
    point (a floor match's two pixels; a sparse floor point's (``sparse_ids``) observations in wide images)
    triangulated again with every frame pose moved along each tangent direction, the plane's least-squares heights
    fitted again on the same inliers (``threshold`` about ``normal @ x + offset = 0``); the tilt with the cameras'
    mean rotation subtracted (what the floor frame's z is compared with); a height is a rigid motion's invariant. A
    sparse point's pixels stand still as a floor match's do: the adjustment moved the point with the poses, so the
    poses' error is the points' shared error here too. None without the points' frames in ``covariance``, or without
    three inliers. Wide images are their rig's reference sensor: their pose is the frame's; another sensor (narrow)
    keeps its place in the rig (its calibration's own uncertainty is not in these heights)."""
    frames = sorted(f for f in reconstruction.reg_frame_ids() if ("frame", f) in covariance.offsets)
    groups = floor_views(reconstruction, matches, sparse_ids, frames)
    if not groups or not frames:
        return None
    index = {f: k for k, f in enumerate(frames)}
    nominal_poses = np.stack([reconstruction.frame(f).rig_from_world.matrix() for f in frames])  # type: ignore[union-attr]
    cameras = [image for image in reconstruction.images.values() if image.has_pose and image.frame_id in index]
    in_rig = np.array([nominal_poses[index[image.frame_id]] @ np.r_[image.projection_center(), 1.0] for image in cameras])
    camera_frames = np.array([index[image.frame_id] for image in cameras], dtype=np.int64)
    a_axis = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a_axis /= np.linalg.norm(a_axis)
    b_axis = np.cross(normal, a_axis)
    axes = np.stack([normal, a_axis, b_axis])

    def points(poses: np.ndarray) -> np.ndarray:
        return np.vstack([triangulate_views(poses, views, rays) for views, rays in groups])

    nominal = points(nominal_poses)
    inliers = np.isfinite(nominal).all(axis=1) & (np.abs(nominal @ normal + offset) < threshold)
    if inliers.sum() < 3:
        return None
    centroid = nominal[inliers].mean(axis=0)
    design = np.c_[np.ones(int(inliers.sum())), (nominal[inliers] - centroid) @ np.stack([a_axis, b_axis]).T]
    solve = np.linalg.pinv(design)  # heights -> (offset, slope along a, slope along b)

    def measures(poses: np.ndarray) -> np.ndarray:
        """The plane's slopes along a and b, then each camera's height above the plane."""
        plane = solve @ ((points(poses)[inliers] - centroid) @ normal)
        rotations, translations = poses[camera_frames, :, :3], poses[camera_frames, :, 3]
        centres = np.einsum("kji,kj->ki", rotations, in_rig - translations)  # R^T (x_rig - t)
        local = (centres - centroid) @ axes.T  # height along the normal, in-plane a and b
        return np.r_[plane[1:], local[:, 0] - (plane[0] + plane[1] * local[:, 1] + plane[2] * local[:, 2])]

    size = covariance.covariance.shape[0]
    jacobian = np.zeros((2 + len(cameras), size))
    in_plane = np.stack([a_axis, b_axis])
    for k_frame, f in enumerate(frames):
        rotation, translation = nominal_poses[k_frame][:, :3], nominal_poses[k_frame][:, 3]
        columns = covariance.slice(("frame", f))
        for k in range(6):
            step = np.zeros(6)
            step[k] = STEP
            moved = nominal_poses.copy()
            moved[k_frame] = _pose(rotation, translation, step[:3], step[3:])
            up = measures(moved)
            moved[k_frame] = _pose(rotation, translation, -step[:3], -step[3:])
            down = measures(moved)
            jacobian[:, columns.start + k] = (up - down) / (2 * STEP)
        # a slope s along a tilts the normal by -s a; the cameras' mean rotation turns what they see by -theta: the
        # frame's world-frame rotation -R^T w, averaged over the frames, moves the normal seen from the cameras by
        # -(mean theta) x normal
        jacobian[:2, columns.start:columns.start + 6] *= -1.0
        d_theta = -rotation.T / len(frames)  # 3x3 on w
        jacobian[:2, columns.start:columns.start + 3] -= in_plane @ (-skew(normal)) @ d_theta
    moved_together = jacobian @ covariance.covariance @ jacobian.T
    heights = np.sqrt(np.maximum(np.diag(moved_together)[2:], 0.0))
    return moved_together[:2, :2], {image.name: float(h) for image, h in zip(cameras, heights)}
