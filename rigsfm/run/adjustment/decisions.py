"""Hold or refine: per rig, whether the images inform its calibration enough, and the network's refinement agrees
with rigs.yaml, for the refined calibration to be kept (:func:`hold_or_refine`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from rigsfm.core.names import name_of
from rigsfm.run.adjustment.model import sensor_from_rig_view
from rigsfm.run.adjustment.result import AdjustResult, CalibrationDecision, JointCovariance

# Directions whose prior variance the images reduce by less are left out of the consistency test: the final solve
# stops with up to FINAL_SETTLE_CHI2 (0.04) of chi^2 left to gain, which adds up to 0.04 / g to the test along a
# direction of gain g (0.4 at this floor), and a rig none of whose directions reaches it is barely observed.
MIN_GAIN = 0.1
HOLD_QUANTILE = 0.95  # of the consistency test
CONTRADICTED_QUANTILE = 0.999  # of the same test: beyond it, say so (chance alone crosses it once in a thousand)
# A network of fewer rigs is held: with two, every calibration change is seen through one pair's matches, whose own
# errors (wrong clicks, a narrow overlap) it absorbs as readily as it corrects rigs.yaml, and the tests below do not
# tell the refinements that lose to rigs.yaml from those that win (benchmarks/README.md, "Refine the calibration or
# hold it").
MIN_RIGS_TO_REFINE = 3


@dataclass(frozen=True)
class _CalibrationChange:
    """The refined-minus-rigs.yaml change of the observed calibration (the covariance's tangent), over the parameters
    with a non-zero prior sigma: ``delta``, the prior and posterior covariances, and each coordinate's rig."""

    delta: np.ndarray
    prior: np.ndarray
    posterior: np.ndarray
    rigs: np.ndarray
    excess: np.ndarray | None = None  # JointCovariance.change_excess over the same coordinates


def _calibration_change(result: AdjustResult, covariance: JointCovariance) -> _CalibrationChange:
    rec, priors = result.reconstruction, result.priors
    calibration = {r.name: r for r in result.rigs}
    keys, changes, prior_blocks, owners = [], [], [], []
    for image in sorted(rec.images.values(), key=lambda im: im.image_id):
        name = name_of(image)
        if not image.has_pose or name.rig not in calibration:
            continue
        key = ("camera", image.camera_id)
        if key in covariance.offsets and key not in covariance.prior_only and key not in keys:
            keys.append(key)
            changes.append(np.asarray(rec.cameras[image.camera_id].params)
                           - np.asarray(calibration[name.rig].camera(name.sensor).params))
            # priors are set with covariance
            prior_blocks.append(np.diag(priors[name.rig].sensor(name.sensor) ** 2))  # type: ignore[index]
            owners += [name.rig] * len(changes[-1])
        key = ("sensor_from_rig", image.camera_id)
        if name.is_narrow and key in covariance.offsets and key not in covariance.prior_only and key not in keys:
            keys.append(key)
            sensor = sensor_from_rig_view(rec, rec.frame(image.frame_id).rig_id, rec.cameras[image.camera_id].sensor_id)
            given = calibration[name.rig].narrow_from_wide
            turn = sensor.rotation * given.rotation.inverse()  # R = Exp(w) R_yaml: w is its rotation vector
            quat = np.asarray(turn.quat)  # x, y, z, w
            axis = quat[:3] / max(float(np.linalg.norm(quat[:3])), 1e-300) * (1.0 if quat[3] >= 0 else -1.0)
            changes.append(np.r_[axis * turn.angle(), np.asarray(sensor.translation) - np.asarray(given.translation)])
            # priors are set with covariance
            prior_blocks.append(priors[name.rig].narrow_from_wide)  # type: ignore[index]
            owners += [name.rig] * 6
    size = sum(len(c) for c in changes)
    prior = np.zeros((size, size))
    at = 0
    for block in prior_blocks:
        prior[at:at + len(block), at:at + len(block)] = block
        at += len(block)
    keep = np.diag(prior) > 0  # sigma 0: held exactly by the prior itself
    posterior = covariance.sub(keys) if keys else np.zeros((0, 0))
    excess = None
    if covariance.change_excess is not None and keys:
        index = covariance.index(keys)
        excess = covariance.change_excess[np.ix_(index, index)][np.ix_(keep, keep)]
    delta = np.concatenate(changes) if changes else np.zeros(0)
    return _CalibrationChange(delta[keep], prior[np.ix_(keep, keep)], posterior[np.ix_(keep, keep)],
                              np.asarray(owners, dtype=object)[keep], excess)


def _directions(prior: np.ndarray, posterior: np.ndarray, delta: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The share ``g_k`` of the prior variance the images removed along each eigen-direction ``v_k`` of ``I - Q``
    (``Q`` the posterior in the prior's whitened coordinates), the map from the change to its whitened coordinates
    along them (``V^T L^-1``), and the change's coordinates ``z``."""
    inverse = scipy.linalg.solve_triangular(np.linalg.cholesky(prior), np.eye(len(prior)), lower=True)
    gains, vectors = np.linalg.eigh(np.eye(len(prior)) - inverse @ posterior @ inverse.T)
    return gains, vectors.T @ inverse, vectors.T @ (inverse @ delta)


def _chi2(prior: np.ndarray, posterior: np.ndarray, delta: np.ndarray, excess: np.ndarray | None
          ) -> tuple[float, int, np.ndarray]:
    """The consistency test's chi-square over the directions with ``g_k >= MIN_GAIN``, its dof and every direction's
    gain: ``sum z_k^2 / g_k`` where the change spreads as ``prior - posterior`` (its ``g_k`` along ``v_k``), else
    ``z^T (diag(g) + V^T L^-1 excess L^-T V)^-1 z`` over those directions (``excess``: how much wider it spreads)."""
    if not len(delta):
        return 0.0, 0, np.zeros(0)
    gains, rows, z = _directions(prior, posterior, delta)
    tested = gains >= MIN_GAIN
    if excess is None or not tested.any():
        return float(np.sum(z[tested] ** 2 / gains[tested])), int(tested.sum()), gains
    spread = np.diag(gains[tested]) + rows[tested] @ excess @ rows[tested].T
    return float(z[tested] @ np.linalg.solve(spread, z[tested])), int(tested.sum()), gains


def hold_or_refine(result: AdjustResult, covariance: JointCovariance | None) -> list[CalibrationDecision]:
    """Per rig, whether its refined calibration is kept or held at rigs.yaml's values.

    In the prior's whitened coordinates (``u = L^-1 (c - c_yaml)``, ``Sigma = L L^T``) the images remove a share
    ``g_k`` of the prior variance along each eigen-direction ``v_k`` of ``I - L^-1 P L^-T`` (``P`` the posterior
    covariance). Four tests:

    - the network's observability: refine only if some direction of the whole calibration (over all rigs: the
      images inform combinations, such as two rigs' focal lengths against each other) has ``g_k >= 1/2``, i.e. the
      images inform it more than rigs.yaml's sigmas do; below that the posterior is mostly the prior, and a change
      is mostly whatever the images' unmodelled errors (wrong clicks, systematic feature offsets) pulled it to;
    - each rig's observability: ``g_k >= MIN_GAIN`` in some direction of its own calibration (its marginal); a rig
      below it is held (the images neither move nor contradict it);
    - the network's size: at least ``MIN_RIGS_TO_REFINE`` registered rigs; a pair's calibration is held (the paper's
      method: E^sl and the intrinsics from the board);
    - the network's consistency: were priors and images both right, the change would be distributed as ``N(0, I -
      Q)`` (the spread of the posterior mean), so ``sum_k (v_k . u)^2 / g_k`` over the network's directions with
      ``g_k >= MIN_GAIN`` is chi-square with that many degrees of freedom (where the solve counts a static rig's
      repeated views as independent, which the covariance does not, the change spreads wider:
      ``JointCovariance.change_excess`` joins ``I - Q``; :func:`_chi2`); above the ``HOLD_QUANTILE`` quantile the
      images moved the calibration further than their information allows, and every rig is held. One test for the
      network, not one per rig: the rigs' calibrations meet in the shared poses, so a rig held at values the images
      contradict pushes that contradiction into the rigs still refined (their intrinsics and every pose), which is
      worse than holding them all or none. Each rig's own chi-square is reported with its decision.

    Without a covariance (a rank-deficient problem) every rig is held."""
    from scipy.stats import chi2 as chi2_distribution  # scipy.stats takes a while to import

    rigs = sorted({name_of(im).rig for im in result.reconstruction.images.values() if im.has_pose}
                  & {r.name for r in result.rigs})
    if covariance is None:
        return [CalibrationDecision(rig, True, "no covariance to test its refinement against") for rig in rigs]
    change = _calibration_change(result, covariance)
    network_chi2, network_dof, network_gains = _chi2(change.prior, change.posterior, change.delta, change.excess)
    network_gain = float(network_gains.max(initial=0.0))
    network_limit = float(chi2_distribution.ppf(HOLD_QUANTILE, network_dof)) if network_dof else 0.0
    decisions = []
    for rig in rigs:
        mine = change.rigs == rig
        if not mine.any():
            decisions.append(CalibrationDecision(rig, True, "no image observes its calibration"))
            continue
        chi2, dof, gains = _chi2(change.prior[np.ix_(mine, mine)], change.posterior[np.ix_(mine, mine)],
                                 change.delta[mine], None if change.excess is None else change.excess[np.ix_(mine, mine)])
        limit = float(chi2_distribution.ppf(HOLD_QUANTILE, dof)) if dof else 0.0
        largest = float(gains.max())
        if network_gain < 0.5:
            held, reason = True, (f"the images inform no direction of the network's calibration more than rigs.yaml's "
                                  f"sigmas do (they remove at most {int(100 * max(network_gain, 0.0))} % of one's prior "
                                  "variance)")
        elif len(rigs) < MIN_RIGS_TO_REFINE:
            held, reason = True, (f"a network of {len(rigs)} rigs: one pair's matches cannot tell a change of the "
                                  "calibration from their own errors, so rigs.yaml's is held")
        elif not dof:
            held, reason = True, (f"the images barely observe its calibration (at most {int(100 * max(largest, 0.0))} % "
                                  "of a direction's prior variance removed)")
        elif network_chi2 > network_limit:
            held, reason = True, (f"the refinement moved the network's calibration further than the images' "
                                  f"information allows (chi-square {network_chi2:.1f} > {network_limit:.1f}, "
                                  f"{network_dof} dof; this rig's {chi2:.1f} against {limit:.1f}): every rig held")
        else:
            held, reason = False, (f"the images inform it (up to {100 * largest:.0f} % of a direction's prior variance "
                                   f"removed) and the network's refinement agrees with rigs.yaml (chi-square "
                                   f"{network_chi2:.1f} <= {network_limit:.1f}, {network_dof} dof; this rig's "
                                   f"{chi2:.1f} against {limit:.1f})")
        decisions.append(CalibrationDecision(rig, held, reason, largest, chi2, dof, limit, network_chi2, network_dof))
    return decisions


def contradiction(decisions: list[CalibrationDecision]) -> str | None:
    """A warning where the images contradict rigs.yaml far beyond its sigmas (the network's consistency test above
    its ``CONTRADICTED_QUANTILE``): every rig is then held at values the images say are off, and the result is
    built on them (a focal length 1 % off on one rig of four put the floor at twice its depth, with no other sign).
    The test sees only what the images inform (a narrow camera's intrinsics not at all without narrow
    observations), and images whose own errors exceed their noise model cross it too (view-dependent features such
    as persons' silhouettes in the wide images), so the message names both causes."""
    from scipy.stats import chi2 as chi2_distribution

    tested = [d for d in decisions if d.network_dof]
    if not tested:
        return None
    network_chi2, dof = tested[0].network_chi2, tested[0].network_dof
    limit = float(chi2_distribution.ppf(CONTRADICTED_QUANTILE, dof))
    if network_chi2 <= limit:
        return None
    worst = max(tested, key=lambda d: d.chi2 / d.limit if d.limit else 0.0)
    return (f"CALIBRATION CONTRADICTED: the images disagree with rigs.yaml far beyond its sigmas (chi-square "
            f"{network_chi2:.1f} > {limit:.1f}, the {100 * CONTRADICTED_QUANTILE:g} % quantile of {dof} dof; most "
            f"{worst.rig}: {worst.chi2:.1f} against {worst.limit:.1f}), and the result holds rigs.yaml's values: "
            f"check {worst.rig}'s entry in rigs.yaml (this resolution? a lens, zoom or focus touched since the "
            "board?) and recalibrate it if it is off: the poses, floor and bands may then be far off; if it is "
            "right, the images' own errors exceed their noise model (persons or other moving or view-dependent "
            "features in the wide images do this too)")
