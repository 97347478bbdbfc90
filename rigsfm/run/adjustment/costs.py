"""Measurement residuals for COLMAP's bundle-adjustment problem (pyceres cost functions with analytic Jacobians).

Every residual here is whitened (divided by its standard uncertainty) and multiplied by ``pixel_sigma``, the
weighting noise of the image observations, so that the whole problem is in pixel units: the reprojection
residuals keep COLMAP's robust loss and the covariance is ``pixel_sigma**2 (J^T J)^-1`` over all residuals.

Pose parameter blocks are COLMAP's ``Rigid3d.params`` ``[qx, qy, qz, qw, tx, ty, tz]`` on the product manifold
(Ceres' ``EigenQuaternionManifold`` x R^3) that COLMAP's bundle adjuster sets: the tangent ``[delta, dt]`` moves
``q' = Quaternion(delta) * q`` (a left rotation by ``w = 2 delta``) and ``t' = t + dt``. Ceres asks a cost
function for the Jacobian with respect to the 7 ambient parameters and multiplies it by the manifold's
``PlusJacobian`` P (4x3, orthonormal columns up to the factor of the quaternion's norm); the functions below
return ``J_delta P^T``, which gives the exact tangent Jacobian under that manifold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap

from rigsfm.core.geometry import skew


def quaternion_plus_jacobian(q_xyzw: np.ndarray) -> np.ndarray:
    """4x3 ``d q' / d delta`` at delta = 0 of Ceres' EigenQuaternionManifold (xyzw storage)."""
    x, y, z, w = (float(c) for c in q_xyzw)
    return np.array([[w, z, -y], [-z, w, x], [y, -x, w], [-x, -y, -z]])  # [w I - [v]x; -v^T]


def rotation_from_params(params: np.ndarray) -> np.ndarray:
    q = np.asarray(params[:4], dtype=np.float64)
    return pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix()


def pose_ambient_jacobian(j_omega: np.ndarray, j_t: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Ambient (n x 7) Jacobian of a residual from its derivatives with respect to ``w`` (rotation vector of a
    left perturbation ``R' = Exp(w) R``) and ``t`` of a Rigid3d block."""
    q = np.asarray(params[:4], dtype=np.float64) / np.linalg.norm(params[:4])
    return np.hstack([2.0 * j_omega @ quaternion_plus_jacobian(q).T, j_t])  # w = 2 delta


@dataclass(frozen=True)
class CentreTerm:
    """One camera centre: ``rig`` indexes (into the cost's parameter blocks) a rig_from_world block; ``sensor``
    indexes a variable sensor_from_rig block, or is None with ``sensor_from_rig`` a constant transform (None
    too: the rig's reference sensor)."""

    rig: int
    sensor: int | None = None
    sensor_from_rig: pycolmap.Rigid3d | None = None


def camera_centre_and_jacobians(term: CentreTerm, blocks: Sequence[np.ndarray], with_jacobians: bool = True):
    """Centre ``c = -R^T (t + R_e^T t_e)`` of ``sensor_from_rig * rig_from_world``, with ``(dc/dw, dc/dt)`` of the
    rig block and (when variable) of the sensor block (None for both without ``with_jacobians``)."""
    rig = blocks[term.rig]
    r, t = rotation_from_params(rig), np.asarray(rig[4:], dtype=np.float64)
    if term.sensor is not None:
        sensor = blocks[term.sensor]
        r_e, t_e = rotation_from_params(sensor), np.asarray(sensor[4:], dtype=np.float64)
    elif term.sensor_from_rig is not None:
        r_e, t_e = term.sensor_from_rig.rotation.matrix(), np.asarray(term.sensor_from_rig.translation)
    else:
        r_e, t_e = np.eye(3), np.zeros(3)
    v = r_e.T @ t_e
    centre = -r.T @ (t + v)
    if not with_jacobians:
        return centre, None, None
    d_rig = (-r.T @ skew(t + v), -r.T)
    d_sensor = (-r.T @ r_e.T @ skew(t_e), -r.T @ r_e.T) if term.sensor is not None else None
    return centre, d_rig, d_sensor


class CameraDistanceCost(pyceres.CostFunction):
    """``pixel_sigma * (|c_a - c_b| - meters) / sigma``: a measured distance between two camera centres, each the
    mean of its ``CentreTerm``s' centres (a camera over several frames). The parameter blocks are 7-vector Rigid3d
    blocks, in the order given to ``add_residual_block``."""

    def __init__(self, terms_a: Sequence[CentreTerm], terms_b: Sequence[CentreTerm], num_blocks: int,
                 meters: float, sigma: float, pixel_sigma: float):
        super().__init__()
        self.terms = (tuple(terms_a), tuple(terms_b))
        self.meters, self.weight = float(meters), pixel_sigma / sigma
        self.num_blocks = num_blocks
        self.set_num_residuals(1)
        self.set_parameter_block_sizes([7] * num_blocks)

    def centres(self, blocks, with_jacobians: bool = True):
        """Both cameras' centres, each with its 3x7 ambient Jacobians per block (None: not in it, or not asked)."""
        out = []
        for terms in self.terms:
            centre, grads = np.zeros(3), [None] * self.num_blocks
            for term in terms:
                c, d_rig, d_sensor = camera_centre_and_jacobians(term, blocks, with_jacobians)
                centre += c / len(terms)
                if not with_jacobians:
                    continue
                for index, d in ((term.rig, d_rig), (term.sensor, d_sensor)):
                    if index is None:
                        continue
                    ambient = pose_ambient_jacobian(d[0], d[1], blocks[index]) / len(terms)  # 3x7
                    # grads starts as Nones, one per block, each replaced by an array
                    grads[index] = ambient if grads[index] is None else grads[index] + ambient  # type: ignore[assignment,operator]
            out.append((centre, grads))
        return out

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - pyceres' name
        (c_a, g_a), (c_b, g_b) = self.centres(parameters, with_jacobians=jacobians is not None)
        diff = c_a - c_b
        distance = float(np.linalg.norm(diff))
        residuals[0] = self.weight * (distance - self.meters)
        if jacobians is not None:
            u = diff / max(distance, 1e-12)
            for k in range(self.num_blocks):
                if jacobians[k] is None:
                    continue
                jac = np.zeros(7)
                if g_a[k] is not None:
                    jac += u @ g_a[k]
                if g_b[k] is not None:
                    jac -= u @ g_b[k]
                jacobians[k][:] = self.weight * jac
        return True


class LengthCost(pyceres.CostFunction):
    """``pixel_sigma * (|X_a - X_b| - meters) / sigma`` between two 3D point blocks (a known length's ends)."""

    def __init__(self, meters: float, sigma: float, pixel_sigma: float):
        super().__init__()
        self.meters, self.weight = float(meters), pixel_sigma / sigma
        self.set_num_residuals(1)
        self.set_parameter_block_sizes([3, 3])

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - pyceres' name
        diff = np.asarray(parameters[0]) - np.asarray(parameters[1])
        length = float(np.linalg.norm(diff))
        residuals[0] = self.weight * (length - self.meters)
        if jacobians is not None:
            u = diff / max(length, 1e-12)
            if jacobians[0] is not None:
                jacobians[0][:] = self.weight * u
            if jacobians[1] is not None:
                jacobians[1][:] = -self.weight * u
        return True
