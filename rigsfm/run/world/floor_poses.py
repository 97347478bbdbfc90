"""The floor's tilt error from the poses' own covariance: the adjustment's joint covariance of the rig poses carried
through the floor matches' triangulation into the plane (the floor points of one image pair share that pair's pose
error, and neighbouring pairs share cameras: a network's errors are correlated, which the points' residuals cannot
show, benchmarks/README.md)."""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.core.geometry import skew
from rigsfm.run.adjustment.result import JointCovariance
from rigsfm.run.world.floor_matching import FloorMatches, triangulate_rays

STEP = 1e-6  # central differences: radians for the rotation, model units for the translation


def _rays(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    return np.asarray(camera.cam_from_img(np.asarray(xy, np.float64).reshape(-1, 2)), np.float64)


def _pose(rotation: np.ndarray, translation: np.ndarray, w: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """``rig_from_world`` moved by the covariance's tangent ``[w, dt]``: R' = Exp(w) R, t' = t + dt."""
    angle = float(np.linalg.norm(w))
    exp = np.eye(3) if angle == 0 else pycolmap.Rotation3d(w).matrix()
    return np.c_[exp @ rotation, translation + dt]


def pose_tilt_covariance(reconstruction: pycolmap.Reconstruction, matches: FloorMatches, normal: np.ndarray,
                         offset: float, threshold: float, covariance: JointCovariance) -> np.ndarray | None:
    """2x2 covariance (radians^2) of the floor's tilt relative to the cameras' mean orientation (the error of the
    normal seen from the cameras, in-plane axes) from the poses' covariance alone: each floor match (its pixels in
    two wide images) triangulated again with every frame pose moved along each tangent direction, the plane's
    least-squares heights fitted again on the same inliers (``threshold`` about ``normal @ x + offset = 0``); the
    cameras' mean rotation subtracted (what the floor frame's z is compared with). None without the matches' frames
    in ``covariance``, or without three inliers. Wide images are their rig's reference sensor: their pose is the
    frame's."""
    images = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    frames = sorted(f for f in reconstruction.reg_frame_ids() if ("frame", f) in covariance.offsets)
    pairs = []
    for m in matches.matches:
        a, b = images.get(m.image_i), images.get(m.image_j)
        if a is None or b is None or not len(m.xy_i) or a.frame_id not in frames or b.frame_id not in frames:
            continue
        if not all(np.array_equal(im.cam_from_world().matrix(),
                                  reconstruction.frame(im.frame_id).rig_from_world.matrix())  # type: ignore[union-attr]  # registered
                   for im in (a, b)):
            continue  # not a reference sensor
        pairs.append((a.frame_id, b.frame_id, _rays(a.camera, m.xy_i), _rays(b.camera, m.xy_j)))  # type: ignore[arg-type]
    if not pairs or not frames:
        return None
    poses = {f: (reconstruction.frame(f).rig_from_world.rotation.matrix(),  # type: ignore[union-attr]
                 np.asarray(reconstruction.frame(f).rig_from_world.translation)) for f in frames}  # type: ignore[union-attr]
    a_axis = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a_axis /= np.linalg.norm(a_axis)
    b_axis = np.cross(normal, a_axis)

    def points(moved: dict) -> np.ndarray:
        out = []
        for fi, fj, ri, rj in pairs:
            pi = moved[fi] if fi in moved else np.c_[poses[fi][0], poses[fi][1]]
            pj = moved[fj] if fj in moved else np.c_[poses[fj][0], poses[fj][1]]
            out.append(triangulate_rays(pi, pj, ri, rj))
        return np.vstack(out)

    nominal = points({})
    inliers = np.isfinite(nominal).all(axis=1) & (np.abs(nominal @ normal + offset) < threshold)
    if inliers.sum() < 3:
        return None
    centroid = nominal[inliers].mean(axis=0)
    design = np.c_[np.ones(int(inliers.sum())), (nominal[inliers] - centroid) @ np.stack([a_axis, b_axis]).T]
    solve = np.linalg.pinv(design)  # heights -> (offset, slope along a, slope along b)

    def tilt(moved: dict) -> np.ndarray:
        return (solve @ ((points(moved)[inliers] - centroid) @ normal))[1:]

    size = covariance.covariance.shape[0]
    jacobian = np.zeros((2, size))
    in_plane = np.stack([a_axis, b_axis])
    for f in frames:
        rotation, translation = poses[f]
        columns = covariance.slice(("frame", f))
        for k in range(6):
            step = np.zeros(6)
            step[k] = STEP
            up = tilt({f: _pose(rotation, translation, step[:3], step[3:])})
            down = tilt({f: _pose(rotation, translation, -step[:3], -step[3:])})
            # a slope s along a tilts the normal by -s a; the cameras' mean rotation turns what they see by -theta
            d_normal = -(up - down) / (2 * STEP)
            jacobian[:, columns.start + k] += d_normal
        # the frame's world-frame rotation -R^T w, averaged over the frames: the normal seen from the cameras moves
        # by -(mean theta) x normal
        d_theta = -rotation.T / len(frames)  # 3x3 on w
        jacobian[:, columns.start:columns.start + 3] -= in_plane @ (-skew(normal)) @ d_theta
    return jacobian @ covariance.covariance @ jacobian.T
