"""Why the epipolar band covers less than 95 % on crowds of 3D persons: the adjustment's actual error against its
predicted covariance, and which observations carry the error (mrcal-style uncertainty validation).

    python benchmarks/crowd_band.py WORK/NETWORK [--run fixed|default] [--out FILE]      # classes and chi-squares
    ... --sensitivity-only        # the consider sensitivity S dc against the adjustment's answer to rigs.yaml's error
    ... --explain                 # per pair: the band's linear model fed the true error, by group of parameters
    ... --bands-only [--refine]   # the delivered kind of band (FIXED, or the default adjustment) scored, its accuracy
    ... --draws N                 # the FIXED band over N fresh draws of rigs.yaml's error on these observations
    options: --static-only (the truth's static tracks only), --drop-classes person,contour,inconsistent (those
    truth classes removed), --track-test [--track-quantile Q] [--track-min-observations N] [--keep-noise] (a
    truth-free per-track chi-square test; --keep-noise: the second adjustment weighted by the first's noise),
    --pixel-sigma S (the refined adjustment's weighting noise held), --drop-random N SEED, --drop-ids FILE,
    --influence [--influence-drop N | --influence-threshold T] [--influence-rounds K] [--influence-score S]
    [--influence-out FILE] [--with-rule] (each
    track's influence on the refined calibration from the adjustment's own linearisation, no truth, ranked against
    the truth's classes; the top N, or those above T, removed, the noise held),
    --first-frame-only, --loss TRIVIAL|CAUCHY|..., --inflation X

Results and what they say: benchmarks/README.md, "Why the band is narrow on crowds of 3D persons".

``WORK/NETWORK`` is a folder of ``benchmarks/networks.py`` (``scene/`` rendered, ``fixed/`` or ``default/`` run).
The run's mapping model (``<run>/mapping``) is adjusted again with the calibration held (``--fixed-calibration``'s
adjustment), once at rigs.yaml (its realistic error; the consider covariance: image noise plus the calibration's
sigmas) and once at the exact calibration (rigs_exact.yaml; the image-only covariance), then with classes of tracks
removed. For each: the wide rig poses' error against the truth, relative to the frame the gauge holds, whitened by
the predicted covariance (``e^T Sigma^-1 e`` over its dof; per frame too).

Every observation is classified by casting its keypoint's ray through the TRUE camera into the rendered arena at
the image's instant (``rigsfm.synth.scene.trace``): what it hits (ground, wall, object, person), and whether the
surface's depth jumps within ``CONTOUR_PX`` of it (an occluding contour: the keypoint's 3D point depends on the
view). A track is ``static`` when every observation hits a static surface away from contours and their hit points
agree (within ``AGREE_M``); ``person`` when one hits a person; ``contour`` when one sits on a depth jump (and none on
a person); else ``inconsistent`` (static hits that are different 3D points: a wrong match). Each class's
residuals against the truth (the keypoint against its hit point projected by the true camera) are reported.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import warnings
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pyceres  # noqa: E402
import pycolmap  # noqa: E402
import scipy.linalg  # noqa: E402
import yaml  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from benchmarks.metrics import roc_auc  # noqa: E402
from rigsfm.core.names import name_of  # noqa: E402
from rigsfm.run.adjustment.adjust import adjust  # noqa: E402
from rigsfm.run.adjustment.covariance import joint_covariance  # noqa: E402
from rigsfm.run.adjustment.influence import track_influence as product_influence  # noqa: E402
from rigsfm.run.adjustment.model import sensor_from_rig_view  # noqa: E402
from rigsfm.run.options import AdjustOptions, Calibration  # noqa: E402
from rigsfm.run.pipeline import load_inputs  # noqa: E402
from rigsfm.synth.persons import build_crowd  # noqa: E402
from rigsfm.synth.scene import PERSON, SKY, SceneOptions, build_arena, trace  # noqa: E402

logger = logging.getLogger("benchmarks.crowd_band")
CONTOUR_PX = 2.0  # ring radius (px) around a keypoint probed for a depth jump
CONTOUR_JUMP = 0.05  # relative depth change on the ring that makes a contour
AGREE_M = 0.05  # a static track's hit points agree within this (m)
KIND_NAMES = {0: "sky", 1: "ground", 2: "wall", 3: "object", 4: "person"}


def scene_options(scene: Path) -> SceneOptions:
    raw = yaml.safe_load((scene / "scene.yaml").read_text())["options"]
    raw["frame_offsets"] = tuple(tuple(x) for x in raw.get("frame_offsets") or ())
    return SceneOptions(**{k: v for k, v in raw.items() if k in SceneOptions.__dataclass_fields__})


def classify(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, options: SceneOptions) -> dict:
    """Per 3D point id of ``rec``: class, per-observation truth residual (px) and hit kinds (module docstring)."""
    arena = build_arena(options)
    rigs = sorted({name_of(im).rig for im in rec.images.values()})
    times = sorted({f + options.frame_offset(r) for r in rigs for f in range(options.frames_per_rig)})
    crowd = build_crowd(options, times) if options.persons_per_m2 > 0 else None
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = CONTOUR_PX * np.column_stack([np.cos(angles), np.sin(angles)])
    by_image: dict[int, list[tuple[int, int]]] = {}
    for pid, point in rec.points3D.items():
        for e in point.track.elements:
            by_image.setdefault(e.image_id, []).append((pid, e.point2D_idx))
    hits_of: dict[tuple[int, int], tuple] = {}
    for image_id, obs in by_image.items():
        image = rec.images[image_id]
        if not image.has_pose:
            continue
        true_image = truth.find_image_with_name(image.name)
        camera = truth.cameras[true_image.camera_id]
        pose = true_image.cam_from_world()
        name = name_of(image)
        frame = int(image.name.split("frame")[-1].split(".")[0])
        scene = arena if crowd is None else arena.with_persons(crowd.at(frame + options.frame_offset(name.rig)))
        xy = np.array([image.points2D[k].xy for _, k in obs])
        probes = np.concatenate([xy[:, None, :], xy[:, None, :] + ring[None]], axis=1).reshape(-1, 2)
        rays = np.asarray(camera.cam_ray_from_img(probes), dtype=np.float64)
        world_from_cam = pose.inverse().matrix()
        dirs = rays @ world_from_cam[:, :3].T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origin = world_from_cam[:, 3]
        hits = trace(scene, origin, dirs)
        t = hits.t.reshape(len(obs), -1)
        kind = hits.kind.reshape(len(obs), -1)
        centre_t = t[:, 0]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            jump = np.nanmax(np.abs(t[:, 1:] - centre_t[:, None]) / centre_t[:, None], axis=1)
        contour = ~np.isfinite(jump) | (jump > CONTOUR_JUMP) | np.any(kind[:, 1:] != kind[:, :1], axis=1)
        xyz = origin + centre_t[:, None] * dirs.reshape(len(obs), -1, 3)[:, 0]
        for k, (_, idx) in enumerate(obs):
            hits_of[(image_id, idx)] = (int(kind[k, 0]), bool(contour[k]), xyz[k], image, camera, pose)
    out = {}
    for pid, point in rec.points3D.items():
        rows = [hits_of.get((e.image_id, e.point2D_idx)) for e in point.track.elements]
        rows = [r for r in rows if r is not None]
        kinds = [r[0] for r in rows]
        finite = [r[2] for r in rows if r[0] != SKY]
        spread = float(np.max(np.linalg.norm(np.array(finite) - np.mean(finite, axis=0), axis=1))) if finite else np.inf
        if PERSON in kinds:
            cls = "person"
        elif any(r[1] for r in rows) or SKY in kinds:
            cls = "contour"
        elif spread > AGREE_M:
            cls = "inconsistent"
        else:
            cls = "static"
        # Residual against the truth: the keypoint against the mean hit point seen by the true camera.
        centre = np.mean(finite, axis=0) if finite else None
        residuals = []
        for e, r in zip(point.track.elements, rows):
            if centre is None:
                break
            image, camera, pose = r[3], r[4], r[5]
            proj = camera.img_from_cam(pose * centre)
            if proj is not None:
                residuals.append(float(np.linalg.norm(np.asarray(proj) - image.points2D[e.point2D_idx].xy)))
        out[pid] = {"class": cls, "kinds": kinds, "spread_m": spread, "residuals": residuals}
    return out


def hold_pixel_sigma(sigma: float) -> None:
    """The refined adjustment weights the images by ``sigma`` (px) instead of re-estimating it from the residuals
    (and a held network reports it): the noise, and with it the posterior and the hold-or-refine test, as with every
    track while tracks are removed."""
    import rigsfm.run.adjustment.adjust as adjust_module

    adjust_module.estimate_pixel_sigma = lambda *_args, **_kwargs: sigma


def inconsistent_tracks(rec: pycolmap.Reconstruction, quantile: float = 0.999, min_observations: int = 2) -> set[int]:
    """Tracks whose reprojection residuals a static point does not explain: ``sum e^2 / sigma^2`` above the
    chi-square ``quantile`` of its ``2 n - 3`` dof, ``sigma`` from the median track (robust to the few that are not
    static points); only tracks of ``min_observations`` or more are judged."""
    from scipy.stats import chi2

    sums, dofs, ids = [], [], []
    for pid, point in rec.points3D.items():
        total, n = 0.0, 0
        for e in point.track.elements:
            image = rec.images[e.image_id]
            proj = rec.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point.xyz)
            if proj is None:
                continue
            total += float(np.sum((np.asarray(proj) - image.points2D[e.point2D_idx].xy) ** 2))
            n += 1
        if 2 * n - 3 > 0 and n >= min_observations:
            sums.append(total)
            dofs.append(2 * n - 3)
            ids.append(pid)
    sums, dofs = np.array(sums), np.array(dofs)
    sigma2 = float(np.median(sums / chi2.median(dofs)))
    bad = sums / sigma2 > chi2.ppf(quantile, dofs)
    logger.info("track test: sigma %.3f px per coordinate, %d of %d tracks inconsistent", np.sqrt(sigma2),
                int(bad.sum()), len(ids))
    return {pid for pid, b in zip(ids, bad) if b}


def track_influence(result, with_deltas: bool = False, robust: bool = False):
    """Per 3D point id of ``result`` (a REFINE adjustment): how far deleting the track would move the refined
    calibration, from the adjustment's own linearisation (squared loss at the solution, priors in; no truth).
    With the point eliminated, the track's reduced Jacobian ``A = P J_a`` and residual ``e = P r`` (``P`` the
    projector off the point's 3 columns); deleting it moves the other parameters by
    ``d = H^-1 A^T (I - L)^-1 e`` (Woodbury downdate of the reduced normal matrix ``H``; ``L = A H^-1 A^T`` its
    leverage), scored as ``d_c^T Sigma_c^-1 d_c`` with ``Sigma_c = sigma^2 (H^-1)_cc`` (Cook's distance on the
    calibration), and ``d^T H d / sigma^2`` on every parameter. ``robust``: ``cook_calibration`` is the product's
    score (``rigsfm.run.adjustment.influence.track_influence``: the robust loss's weights in, the one the default
    adjustment's rule uses); the other scores and the deltas stay the squared loss's."""
    from rigsfm.run.adjustment import covariance as cv
    from rigsfm.run.adjustment.problem import JointProblem
    from rigsfm.run.adjustment.result import Gauge, ScaleSource

    rec = pycolmap.Reconstruction(result.reconstruction)
    options = result.options
    gauge = Gauge.TWO_CAMS_FROM_WORLD if result.scale_source == ScaleSource.NONE else Gauge.RIGID
    jp = JointProblem(rec, result.rigs, result.priors, result.scale_spec, options, result.pixel_sigma, gauge=gauge,
                      robust=False, with_priors=True, held_rigs=result.held_rigs)
    problem = jp.problem
    variable = [(key, block, dims) for key, block, _, dims in cv.parameter_entries(jp)[0] if block is not None]
    end_points = [p for p in jp.end_points if jp.has_variable(p)]
    point_ids = [pid for pid, p in rec.points3D.items() if jp.has_variable(p.xyz)]
    blocks = [b for _, b, _ in variable] + end_points + [rec.points3D[pid].xyz for pid in point_ids]
    evaluate = pyceres.EvaluateOptions()
    evaluate.set_parameter_blocks(blocks)
    num_a = sum(len(d) for _, _, d in variable) + 3 * len(end_points)
    jac = cv._csr(problem.evaluate_jacobian(evaluate)).tocsr()
    res = np.asarray(problem.evaluate_residuals(evaluate), dtype=np.float64)
    row_point = cv._row_points(jac, num_a, len(point_ids))
    calibration = np.zeros(num_a, dtype=bool)
    k = 0
    for key, _, dims in variable:
        calibration[k:k + len(dims)] = key[0] != "frame"
        k += len(dims)
    jac_a = jac[:, :num_a].tocsr()
    jac_p = jac[:, num_a:].tocsc()
    order = np.argsort(row_point, kind="stable")
    bounds = np.searchsorted(row_point[order], np.arange(len(point_ids) + 1))
    h = (jac_a.T @ jac_a).toarray()
    per_point = []
    for i in range(len(point_ids)):
        rows = order[bounds[i]:bounds[i + 1]]
        sub = jac_a[rows]
        cols = np.unique(sub.indices)
        ja = sub[:, cols].toarray()
        jpp = jac_p[:, 3 * i:3 * i + 3][rows].toarray()
        hpp_inv = np.linalg.inv(jpp.T @ jpp + cv.DAMPING * np.eye(3))
        proj = np.eye(len(rows)) - jpp @ hpp_inv @ jpp.T
        a = proj @ ja
        h[np.ix_(cols, cols)] -= ja.T @ jpp @ hpp_inv @ jpp.T @ ja
        per_point.append((cols, a, proj @ res[rows], len(rows)))
    h = 0.5 * (h + h.T)
    h_inv = cv._inverse(h)
    if h_inv is None:
        raise RuntimeError("the reduced normal matrix is rank deficient")
    sigma2 = jp.weight_sigma**2
    cal = np.flatnonzero(calibration)
    cal_info = np.linalg.inv(h_inv[np.ix_(cal, cal)])  # (H^-1)_cc^-1; Sigma_c^-1 = this / sigma^2
    out: dict = {}
    deltas: dict[int, np.ndarray] = {}
    for pid, (cols, a, e, n) in zip(point_ids, per_point):
        lev = a @ h_inv[np.ix_(cols, cols)] @ a.T
        x = np.linalg.solve(np.eye(len(e)) - lev, e)
        d = h_inv[:, cols] @ (a.T @ x)
        dc = d[cal]
        deltas[pid] = dc
        out[pid] = {"cook_calibration": float(dc @ cal_info @ dc / sigma2),
                    "cook_all": float(d @ h @ d / sigma2),
                    "leverage": float(np.trace(lev)), "observations": n // 2,
                    "residual_rms_px": float(np.sqrt(np.mean(e**2)))}
    if robust:
        scores = product_influence(result)
        for pid in out:
            out[pid]["cook_calibration"] = scores.get(pid, 0.0)
    logger.info("track influence: %d tracks, %d calibration parameters, sigma %.3f px", len(out), len(cal),
                jp.weight_sigma)
    if with_deltas:
        # the calibration's parameters in d_c's order: (camera id, parameter index)
        params = [(key[1], d) for key, _, dims in variable if key[0] != "frame" for d in dims]
        return out, {"deltas": deltas, "params": params, "info": cal_info / sigma2}
    return out


def check_influence(mapped, given, options, first, influence, linear, count: int) -> None:
    """The downdate against the adjustment: each of the ``count`` most influential tracks deleted alone, the default
    adjustment run again (noise held at ``first``'s), the refined calibration's change against the predicted ``d_c``,
    both scored with the same ``Sigma_c``."""
    hold_pixel_sigma(first.pixel_sigma)
    ranked = sorted(influence, key=lambda p: -influence[p]["cook_calibration"])[:count]
    base = np.array([first.reconstruction.cameras[c].params[d] for c, d in linear["params"]])
    for pid in ranked:
        rec = pycolmap.Reconstruction(mapped)
        rec.delete_point3D(pid)
        again = adjust(rec, given.rigs, given.scale, replace(options, calibration=Calibration.REFINE), given.priors)
        if again.held_rigs or again.calibration != Calibration.REFINE:
            logger.info("track %d: predicted D %.2f; deleted, rigs held %s", pid,
                        influence[pid]["cook_calibration"], sorted(again.held_rigs))
            continue
        actual = np.array([again.reconstruction.cameras[c].params[d] for c, d in linear["params"]]) - base
        predicted = linear["deltas"][pid]
        info = linear["info"]
        logger.info("track %d: D predicted %.2f, actual %.2f; |actual - predicted| / |actual| (whitened) %.2f",
                    pid, predicted @ info @ predicted, actual @ info @ actual,
                    np.sqrt((actual - predicted) @ info @ (actual - predicted) / max(actual @ info @ actual, 1e-30)))


def influence_report(influence: dict, classes: dict, top: tuple[int, ...] = (25, 50, 100, 200)) -> dict:
    """How well each influence score ranks the truth's person and contour tracks: ROC AUC, hits in the top N, the
    classes of the top tracks."""
    ids = [pid for pid in influence if pid in classes]
    target = np.array([classes[p]["class"] in ("person", "contour") for p in ids])
    two_view = np.array([influence[p]["observations"] == 2 for p in ids])
    report = {"tracks": len(ids), "targets": int(target.sum()), "scores": {}}
    for score in ("cook_calibration", "cook_all", "leverage", "residual_rms_px"):
        v = np.array([influence[p][score] for p in ids])
        auc, auc2 = roc_auc(v, target), roc_auc(v[two_view], target[two_view])
        order = np.argsort(-v)
        row = {"auc": auc, "auc_two_view": auc2, "top": {}}
        for n in top:
            sel = order[:n]
            counts: dict[str, int] = {}
            for j in sel:
                counts[classes[ids[j]]["class"]] = counts.get(classes[ids[j]]["class"], 0) + 1
            row["top"][n] = {"targets": int(target[sel].sum()), "classes": counts,
                             "two_view": int(two_view[sel].sum())}
        row["top_ids"] = [int(ids[j]) for j in order[:400]]
        report["scores"][score] = row
        logger.info("%s: AUC %s (two-view only %s); top 25/50/100/200 person+contour %s; top 50 classes %s", score,
                    f"{auc:.3f}" if auc is not None else "-", f"{auc2:.3f}" if auc2 is not None else "-",
                    [row["top"][n]["targets"] for n in top], row["top"][50]["classes"])
    return report


def frame_key(rec: pycolmap.Reconstruction, frame_id: int) -> str:
    frame = rec.frame(frame_id)
    ref = next(rec.image(d.id) for d in frame.image_ids if rec.image(d.id).is_ref_in_frame())
    return ref.name


def pose_errors(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, cov, gauge_frame: int) -> dict:
    """Whitened error of every frame's pose (relative to ``gauge_frame``, aligned to the truth there)."""
    def true_pose(frame_id: int) -> pycolmap.Rigid3d:
        image = truth.find_image_with_name(frame_key(rec, frame_id))
        return truth.frame(image.frame_id).rig_from_world

    ref_est = rec.frame(gauge_frame).rig_from_world
    align = ref_est.inverse() * true_pose(gauge_frame)  # truth world -> estimate world
    frames = [f for f in sorted(rec.reg_frame_ids()) if f != gauge_frame]
    errors = []
    for f in frames:
        est = rec.frame(f).rig_from_world * align
        tru = true_pose(f)
        w = Rotation.from_matrix(est.rotation.matrix() @ tru.rotation.matrix().T).as_rotvec()
        dt = np.asarray(est.translation) - np.asarray(tru.translation)
        errors.append(np.r_[w, dt])
    e = np.concatenate(errors)
    sub = cov.sub([("frame", f) for f in frames])
    chi2 = float(e @ np.linalg.lstsq(sub, e, rcond=1e-12)[0])
    per_frame = {}
    for k, f in enumerate(frames):
        block = sub[6 * k:6 * k + 6, 6 * k:6 * k + 6]
        ek = e[6 * k:6 * k + 6]
        per_frame[frame_key(rec, f)] = {
            "chi2": float(ek @ np.linalg.lstsq(block, ek, rcond=1e-12)[0]),
            "rotation_deg": float(np.degrees(np.linalg.norm(ek[:3]))),
            "rotation_sigma_deg": float(np.degrees(np.sqrt(np.trace(block[:3, :3])))),
            "translation_mm": 1000 * float(np.linalg.norm(ek[3:])),
            "translation_sigma_mm": 1000 * float(np.sqrt(np.trace(block[3:, 3:])))}
    return {"chi2": chi2, "dof": int(len(e)), "chi2_over_dof": chi2 / len(e), "frames": per_frame}


def consider_sensitivity(result, given, exact, options, unweighted=False, robust=False):
    """``S = -A^-1 B`` of ``covariance._consider`` at ``result`` (our tangents), the calibration's true error ``dc``
    (rigs.yaml minus rigs_exact.yaml) and its prior, the pose rows and each frame's first row."""
    from rigsfm.run.adjustment import covariance as cv
    from rigsfm.run.adjustment.model import estimate_pixel_sigma
    from rigsfm.run.adjustment.problem import JointProblem
    from rigsfm.run.adjustment.result import Gauge

    rec = pycolmap.Reconstruction(result.reconstruction)
    sigma = estimate_pixel_sigma(rec, options.max_reprojection_error_px)
    jp = JointProblem(rec, result.rigs, result.priors, result.scale_spec, options, sigma, gauge=Gauge.RIGID,
                      robust=robust, with_priors=False, consider_held=True)
    saved = cv.repeated_view_correlation
    if unweighted:
        cv.repeated_view_correlation = lambda *a, **k: {}
    try:
        schur, entries, variable, prior_only, *_ = cv._reduced_system(jp, options.max_reprojection_error_px,
                                                                  options.pixel_sigma_inflation)
    finally:
        cv.repeated_view_correlation = saved
    factors = cv._tangent_factors(variable)
    factors = np.r_[factors, np.ones(schur.shape[0] - len(factors))]
    scaled = schur / np.outer(factors, factors)
    exact_by = {r.name: r for r in exact.rigs}
    given_by = {r.name: r for r in given.rigs}
    pose_index, cal_index, dc, prior, frame_at, labels = [], [], [], [], {}, []
    k = 0
    for key, _, _, dims in variable:
        if key[0] == "frame":
            frame_at[key[1]] = k
            pose_index.extend(range(k, k + len(dims)))
        else:
            name = jp.camera_names[key[1]]
            if key[0] == "camera":
                delta = (np.asarray(given_by[name.rig].camera(name.sensor).params)
                         - np.asarray(exact_by[name.rig].camera(name.sensor).params))
                block = np.diag(jp.camera_sigmas(key[1]) ** 2)
            else:
                g, e = given_by[name.rig].narrow_from_wide, exact_by[name.rig].narrow_from_wide
                w = Rotation.from_matrix(g.rotation.matrix() @ e.rotation.matrix().T).as_rotvec()
                delta = np.r_[w, np.asarray(g.translation) - np.asarray(e.translation)]
                block = jp.priors[name.rig].narrow_from_wide
            dc.append(delta[dims])
            labels.extend(f"{name.rig}/{name.sensor} {key[0]}[{d}]" for d in dims)
            prior.append(block[np.ix_(dims, dims)])
            cal_index.extend(range(k, k + len(dims)))
        k += len(dims)
    pose_index += list(range(k, schur.shape[0]))
    dc = np.concatenate(dc)
    prior = scipy.linalg.block_diag(*prior)
    a = scaled[np.ix_(pose_index, pose_index)]
    b = scaled[np.ix_(pose_index, cal_index)]
    s = -np.linalg.solve(a, b)
    return s, dc, prior, pose_index, frame_at, labels


def sensitivity_check(mapped, truth, given, exact, options, remove=frozenset(), unweighted=False,
                      robust=False) -> dict:
    """The consider model's linear claim, tested: the poses of the rigs.yaml adjustment minus those of the exact
    calibration's (same observations) against ``S dc`` (``S = -A^-1 B`` of ``covariance._consider``, ``dc`` the
    calibration's true error), and ``dc``'s chi-square under rigs.yaml's sigmas. ``unweighted``: S without the
    repeated-view weights (the estimator the solver actually is)."""

    results = {}
    for label, inputs in (("given", given), ("exact", exact)):
        rec = pycolmap.Reconstruction(mapped)
        for pid in remove:
            if rec.exists_point3D(pid):
                rec.delete_point3D(pid)
        results[label] = adjust(rec, inputs.rigs, inputs.scale, replace(options, calibration=Calibration.FIXED),
                                inputs.priors)
    result = results["given"]
    s, dc, prior, pose_index, frame_at, _ = consider_sensitivity(result, given, exact, options, unweighted,
                                                                robust)
    predicted = s @ dc
    # The actual difference, aligned at the gauge frame (the rigs.yaml run onto the exact run).
    given_rec, exact_rec = results["given"].reconstruction, results["exact"].reconstruction
    gauge_frame = min(given_rec.reg_frame_ids())
    align = given_rec.frame(gauge_frame).rig_from_world.inverse() * exact_rec.frame(gauge_frame).rig_from_world
    rows, actual_all, predicted_all = {}, [], []
    for f, at in sorted(frame_at.items()):
        est = given_rec.frame(f).rig_from_world * align
        ref = exact_rec.frame(f).rig_from_world
        w = Rotation.from_matrix(est.rotation.matrix() @ ref.rotation.matrix().T).as_rotvec()
        actual = np.r_[w, np.asarray(est.translation) - np.asarray(ref.translation)]
        pos = pose_index.index(at)
        pred = predicted[pos:pos + 6]
        actual_all.append(actual)
        predicted_all.append(pred)
        from rigsfm.run.adjustment.covariance import frame_centre_jacobian
        centre, d_centre = frame_centre_jacobian(ref)
        origin = frame_centre_jacobian(exact_rec.frame(gauge_frame).rig_from_world)[0]
        direction = (centre - origin) / max(np.linalg.norm(centre - origin), 1e-9)
        radial_actual = float(direction @ (frame_centre_jacobian(est)[0] - centre))
        radial_predicted = float(direction @ (d_centre @ pred))
        rows[frame_key(given_rec, f)] = {
            "radial_actual_mm": 1000 * radial_actual, "radial_predicted_mm": 1000 * radial_predicted,
            "actual_rotation_deg": float(np.degrees(np.linalg.norm(actual[:3]))),
            "predicted_rotation_deg": float(np.degrees(np.linalg.norm(pred[:3]))),
            "actual_translation_mm": 1000 * float(np.linalg.norm(actual[3:])),
            "predicted_translation_mm": 1000 * float(np.linalg.norm(pred[3:])),
            "rotation_difference_deg": float(np.degrees(np.linalg.norm(actual[:3] - pred[:3]))),
            "translation_difference_mm": 1000 * float(np.linalg.norm(actual[3:] - pred[3:]))}
    actual_all, predicted_all = np.concatenate(actual_all), np.concatenate(predicted_all)
    cov_pred = (s @ prior @ s.T)
    idx = [pose_index.index(at) + d for _, at in sorted(frame_at.items()) for d in range(6)]
    cov_pred = cov_pred[np.ix_(idx, idx)]
    out = {"dc_chi2": float(dc @ np.linalg.solve(prior, dc)), "dc_dof": int(len(dc)),
           "unweighted": unweighted, "removed_points": len(remove),
           "actual_chi2_under_S_prior_ST": float(actual_all @ np.linalg.lstsq(cov_pred, actual_all, rcond=1e-12)[0]),
           "predicted_chi2_under_S_prior_ST": float(
               predicted_all @ np.linalg.lstsq(cov_pred, predicted_all, rcond=1e-12)[0]),
           "relative_residual": float(np.linalg.norm(actual_all - predicted_all) / np.linalg.norm(actual_all)),
           "frames": rows}
    logger.info("sensitivity (%s, %d removed): dc chi2 %.1f / %d; actual vs S dc: relative residual %.2f; "
                "chi2 actual %.1f, predicted %.1f (%d dof)", "unweighted" if unweighted else "weighted",
                len(remove), out["dc_chi2"], out["dc_dof"], out["relative_residual"],
                out["actual_chi2_under_S_prior_ST"], out["predicted_chi2_under_S_prior_ST"], len(idx))
    return out


def true_floor(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction):
    """The truth's floor (z = 0) in ``rec``'s frame: a similarity of the wide centres onto the truth's."""
    from rigsfm.core.geometry import Plane

    est, tru = [], []
    for image in rec.images.values():
        if image.has_pose and name_of(image).sensor == "wide":
            est.append(image.projection_center())
            tru.append(truth.find_image_with_name(image.name).projection_center())
    est, tru = np.array(est), np.array(tru)
    me, mt = est.mean(0), tru.mean(0)
    u, d, vt = np.linalg.svd((tru - mt).T @ (est - me))
    r = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt  # truth = s R est + t
    scale = np.sum(d * np.diag(np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]))) / np.sum((est - me) ** 2)
    # z_truth = e3 . (s R x + t) = 0  ->  normal R^T e3, offset (e3 . t) / s
    t = mt - scale * r @ me
    normal = r.T @ np.array([0.0, 0.0, 1.0])
    return Plane(normal, float(t[2] / scale), 0)


def calibration_errors(result, cov, exact) -> dict:
    """The adjusted calibration's error against rigs_exact.yaml, whitened by ``cov`` (its calibration block)."""
    rec = result.reconstruction
    exact_by = {r.name: r for r in exact.rigs}
    names = {im.camera_id: name_of(im) for im in rec.images.values()}
    keys, errors, groups = [], [], []
    for key in cov.keys:
        if key[0] == "frame" or key in cov.prior_only:
            continue
        name = names[key[1]]
        if key[0] == "camera":
            e = np.asarray(rec.cameras[key[1]].params) - np.asarray(exact_by[name.rig].camera(name.sensor).params)
        else:
            image = next(im for im in rec.images.values() if im.camera_id == key[1])
            g = sensor_from_rig_view(rec, rec.frame(image.frame_id).rig_id, rec.cameras[key[1]].sensor_id)
            x = exact_by[name.rig].narrow_from_wide
            w = Rotation.from_matrix(g.rotation.matrix() @ x.rotation.matrix().T).as_rotvec()
            e = np.r_[w, np.asarray(g.translation) - np.asarray(x.translation)]
        keys.append(key)
        errors.append(e)
        groups.extend([f"{name.sensor} intrinsics" if key[0] == "camera" else "E^sl"] * len(e))
    e = np.concatenate(errors)
    sub = cov.sub(keys)
    keep = np.diag(sub) > 0
    e, sub = e[keep], sub[np.ix_(keep, keep)]
    groups = np.array(groups)[keep]
    by_group = {}
    for g in sorted(set(groups)):
        m = groups == g
        chi2_g = float(e[m] @ np.linalg.lstsq(sub[np.ix_(m, m)], e[m], rcond=1e-12)[0])
        by_group[g] = {"chi2": chi2_g, "dof": int(m.sum()), "chi2_over_dof": chi2_g / m.sum()}
        logger.info("  %s: chi2/dof %.2f (%d dof)", g, chi2_g / m.sum(), m.sum())
    chi2 = float(e @ np.linalg.lstsq(sub, e, rcond=1e-12)[0])
    z = e / np.sqrt(np.diag(sub))
    return {"chi2": chi2, "dof": int(len(e)), "chi2_over_dof": chi2 / len(e), "groups": by_group,
            "rms_z": float(np.sqrt(np.mean(z**2))), "max_abs_z": float(np.max(np.abs(z)))}


def band_experiment(mapped, truth, inputs, options, exact_inputs=None, floor=True) -> dict:
    """The delivered kind of band against the truth: analysis points at every depth (no floor found: the persons
    networks) and on the true floor, from the same covariance."""
    from benchmarks.trust import score_bands
    from rigsfm.run.adjustment.bands import narrow_pair_bands

    result = adjust(pycolmap.Reconstruction(mapped), inputs.rigs, inputs.scale, options, inputs.priors)
    cov = result.covariance or joint_covariance(result)
    rec = result.reconstruction
    from benchmarks.hold_or_refine import epipolar_p95
    from benchmarks.metrics import evaluate

    narrow = evaluate(rec, truth, metric=True)["narrow"].get("relative_rotation_deg") or {}
    out = {"calibration": str(result.calibration), "held_rigs": sorted(result.held_rigs),
           "narrow_rotation_deg": {k: narrow.get(k) for k in ("median", "max")},
           "true_epipolar_p95_px": epipolar_p95(rec, truth),
           "poses": pose_errors(rec, truth, cov, min(rec.reg_frame_ids()))}
    logger.info("narrow rotation median / max %s / %s deg, worst pair's true epipolar p95 %.2f px",
                out["narrow_rotation_deg"]["median"], out["narrow_rotation_deg"]["max"], out["true_epipolar_p95_px"])
    logger.info("%s (held %s): wide poses chi2/dof %.2f (%d dof)", result.calibration, sorted(result.held_rigs),
                out["poses"]["chi2_over_dof"], out["poses"]["dof"])
    if exact_inputs is not None and result.calibration == Calibration.REFINE:
        out["calibration_error"] = calibration_errors(result, cov, exact_inputs)
        logger.info("calibration error whitened by the posterior: chi2/dof %.2f (%d dof), rms z %.2f, max |z| %.1f",
                    *(out["calibration_error"][k] for k in ("chi2_over_dof", "dof", "rms_z", "max_abs_z")))
    for label, plane in (("depths", None), ("true floor", true_floor(rec, truth))):
        if label == "true floor" and not floor:
            continue
        bands = narrow_pair_bands(rec, cov, plane=plane)
        rows = score_bands(rec, truth, bands)
        rows = [r for r in rows if r["pair"][0].split("/")[0] != r["pair"][1].split("/")[0]]
        n = sum(r["num_true_points"] for r in rows)
        out[label] = {"pairs": len(rows), "coverage": sum(r["coverage"] * r["num_true_points"] for r in rows) / n,
                      "band_median_px": float(np.median([r["band_px"] for r in rows])),
                      "true_p95_median_px": float(np.median([r["true_p95_px"] for r in rows])),
                      "rows": rows}
        # The model's own distribution of this network's pooled coverage: the draws are shared by the pairs.
        weights = {tuple(r["pair"]): r["num_true_points"] for r in rows}
        per_draw = sum(bands[k].predicted_coverage * w for k, w in weights.items()) / n
        out[label]["predicted_network_coverage"] = {
            "median": float(np.median(per_draw)), "p05": float(np.quantile(per_draw, 0.05)),
            "share_at_or_below_observed": float(np.mean(per_draw <= out[label]["coverage"]))}
        logger.info("  the model's network coverage: median %.3f, 5 %% quantile %.3f, P(<= observed) %.3f",
                    *out[label]["predicted_network_coverage"].values())
        logger.info("bands at %s: %d pairs, coverage %.3f, band median %.2f px, true p95 median %.2f px", label,
                    len(rows), out[label]["coverage"], out[label]["band_median_px"], out[label]["true_p95_median_px"])
    return out


def draws_experiment(mapped, truth, given, exact, options, draws: int) -> dict:
    """The band over calibration draws on this network's own observations: rigs.yaml's error drawn anew
    (``rigsfm.synth.cameras.perturb_rig_from``, the renderer's own error model; sigmas kept), the fixed-calibration
    adjustment and its linear bands each time, scored against the truth (what ``benchmarks/band_truth.py`` does on
    a featureless circle). The network's coverage per draw, and the pooled one."""
    from benchmarks.trust import score_bands
    from rigsfm.run.adjustment.bands import narrow_pair_bands
    from rigsfm.synth.cameras import perturb_rig_from

    rows = []
    for k in range(draws):
        rng = np.random.default_rng([1000 + k, 31])
        rigs = tuple(replace(g, **{f: getattr(perturb_rig_from(x, rng), f)
                                   for f in ("wide", "narrow", "narrow_from_wide")})
                     for g, x in zip(given.rigs, exact.rigs))
        inputs = replace(given, rigs=rigs)
        result = adjust(pycolmap.Reconstruction(mapped), rigs, inputs.scale,
                        replace(options, calibration=Calibration.FIXED), inputs.priors)
        cov = joint_covariance(result)
        rec = result.reconstruction
        scored = [r for r in score_bands(rec, truth, narrow_pair_bands(rec, cov))
                  if r["pair"][0].split("/")[0] != r["pair"][1].split("/")[0]]
        n = sum(r["num_true_points"] for r in scored)
        inside = sum(r["coverage"] * r["num_true_points"] for r in scored)
        rows.append({"draw": k, "coverage": inside / n, "points": n,
                     "band_median_px": float(np.median([r["band_px"] for r in scored])),
                     "true_p95_median_px": float(np.median([r["true_p95_px"] for r in scored]))})
        logger.info("draw %d: coverage %.3f, band median %.2f px, true p95 median %.2f px", k, rows[-1]["coverage"],
                    rows[-1]["band_median_px"], rows[-1]["true_p95_median_px"])
    pooled = sum(r["coverage"] * r["points"] for r in rows) / sum(r["points"] for r in rows)
    logger.info("%d draws: pooled coverage %.3f, per draw median %.3f, min %.3f", draws, pooled,
                np.median([r["coverage"] for r in rows]), min(r["coverage"] for r in rows))
    return {"draws": rows, "pooled_coverage": pooled}


def explain_pairs(mapped, truth, given, exact, options) -> dict:
    """Per inter-rig narrow pair: the band's own linear model ``d = J z`` fed the TRUE error ``z`` (estimate minus
    truth of the wide poses, aligned at the gauge frame; E^sl and intrinsics against rigs_exact.yaml) at true floor
    points, against the actual distances; and per group of parameters its share of ``J z`` and its predicted sigma
    (``sqrt(J_g Sigma_g J_g^T)``), so the group that errs beyond its sigma shows."""
    from benchmarks.trust import score_bands
    from rigsfm.run.adjustment.bands import (
        PairModel,
        band_points,
        narrow_pair_bands,
        registered_narrow_images,
    )

    result = adjust(pycolmap.Reconstruction(mapped), given.rigs, given.scale,
                    replace(options, calibration=Calibration.FIXED), given.priors)
    cov = joint_covariance(result)
    rec = result.reconstruction
    gauge_frame = min(rec.reg_frame_ids())

    def true_pose(frame_id):
        image = truth.find_image_with_name(frame_key(rec, frame_id))
        return truth.frame(image.frame_id).rig_from_world

    align = rec.frame(gauge_frame).rig_from_world.inverse() * true_pose(gauge_frame)
    exact_by = {r.name: r for r in exact.rigs}
    names = {im.camera_id: name_of(im) for im in rec.images.values()}
    z = np.zeros(cov.covariance.shape[0])
    for key in cov.keys:
        sl = cov.slice(key)
        if key[0] == "frame":
            est, tru = rec.frame(key[1]).rig_from_world * align, true_pose(key[1])
            w = Rotation.from_matrix(est.rotation.matrix() @ tru.rotation.matrix().T).as_rotvec()
            z[sl] = np.r_[w, np.asarray(est.translation) - np.asarray(tru.translation)]
        elif key[0] == "camera":
            name = names[key[1]]
            z[sl] = np.asarray(rec.cameras[key[1]].params) - np.asarray(exact_by[name.rig].camera(name.sensor).params)
        else:
            name = names[key[1]]
            image = next(im for im in rec.images.values() if im.camera_id == key[1] and im.has_pose)
            g = sensor_from_rig_view(rec, rec.frame(image.frame_id).rig_id, rec.cameras[key[1]].sensor_id)
            x = exact_by[name.rig].narrow_from_wide
            w = Rotation.from_matrix(g.rotation.matrix() @ x.rotation.matrix().T).as_rotvec()
            z[sl] = np.r_[w, np.asarray(g.translation) - np.asarray(x.translation)]
    sens, dc, prior, pose_index, frame_at, labels = consider_sensitivity(result, given, exact, options)
    plane = true_floor(rec, truth)
    bands = narrow_pair_bands(rec, cov, plane=plane)
    scored = {tuple(r["pair"]): r for r in score_bands(rec, truth, bands)}
    images = {im.name: im for im in registered_narrow_images(rec)}
    rows = []
    for (a, b), row in sorted(scored.items()):
        if a.split("/")[0] == b.split("/")[0]:
            continue
        model = PairModel(rec, cov, images[a], images[b], {})
        pixels, depths, _ = band_points(rec, images[a], images[b], plane)
        jac = model.jacobian(pixels, depths)
        zk = np.concatenate([z[cov.slice(k)] for k in model.keys])
        groups = {"poses": ("frame",), "E^sl": ("sensor_from_rig",), "intrinsics": ("camera",)}
        out = {"pair": [a, b], "band_px": row["band_px"], "actual_median_px": row["true_median_px"],
               "predicted_median_px": float(np.median(np.abs(jac @ zk)))}
        for g, kinds in groups.items():
            mask = np.concatenate([np.full(cov.offsets[k][1], k[0] in kinds) for k in model.keys])
            part = jac[:, mask] @ zk[mask]
            sigma = np.sqrt(np.einsum("pk,kl,pl->p", jac[:, mask], model.covariance[np.ix_(mask, mask)],
                                      jac[:, mask]))
            out[g] = {"value_px": float(np.median(part)), "sigma_px": float(np.median(sigma))}
        # The poses' share predicted from the calibration's true error, S dc, and which parameters make it.
        jac_pose = np.zeros((len(jac), len(pose_index)))
        for k in model.keys:
            if k[0] == "frame" and k[1] in frame_at:  # the gauge's frame is held
                at = pose_index.index(frame_at[k[1]])
                jac_pose[:, at:at + 6] = jac[:, np.concatenate(
                    [np.full(cov.offsets[q][1], q == k) for q in model.keys])]
        u = np.median(jac_pose, axis=0) @ sens  # d (median point's distance) / d calibration
        contributions = u * dc
        order = np.argsort(-np.abs(contributions))[:4]
        out["poses_from_S_dc_px"] = float(u @ dc)
        out["poses_from_S_dc_sigma_px"] = float(np.sqrt(u @ prior @ u))
        out["top"] = [(labels[q], float(contributions[q]), float(abs(u[q]) * np.sqrt(prior[q, q]))) for q in order]
        sigma_all = np.sqrt(np.einsum("pk,kl,pl->p", jac, model.covariance, jac))
        out["sigma_px"] = float(np.median(sigma_all))
        rows.append(out)
        print(f"{a.split('/')[0]}/{a[-8:-4]}-{b.split('/')[0]}/{b[-8:-4]}: band {out['band_px']:5.2f} actual "
              f"{out['actual_median_px']:5.2f} J z {out['predicted_median_px']:5.2f} sigma {out['sigma_px']:5.2f} | "
              + " | ".join(f"{g} {out[g]['value_px']:+6.2f} (s {out[g]['sigma_px']:5.2f})" for g in groups)
              + f" | S dc {out['poses_from_S_dc_px']:+6.2f} (s {out['poses_from_S_dc_sigma_px']:5.2f}) top "
              + ", ".join(f"{t[0]} {t[1]:+.2f} (s {t[2]:.2f})" for t in out["top"]))
    return {"pairs": rows}


def experiment(mapped, truth, inputs, options, label, remove=frozenset(), image_only=False) -> dict:
    rec = pycolmap.Reconstruction(mapped)
    for pid in remove:
        if rec.exists_point3D(pid):
            rec.delete_point3D(pid)
    result = adjust(rec, inputs.rigs, inputs.scale, replace(options, calibration=Calibration.FIXED), inputs.priors)
    cov = joint_covariance(result, image_only=image_only)
    gauge_frame = min(result.reconstruction.reg_frame_ids())
    row = {"label": label, "removed_points": len(remove), "points": result.reconstruction.num_points3D(),
           "gauge": str(result.gauge), "weight_sigma_px": cov.pixel_sigma,
           **pose_errors(result.reconstruction, truth, cov, gauge_frame)}
    logger.info("%s: chi2/dof %.2f (%d dof), weight sigma %.3f px, %d points", label, row["chi2_over_dof"],
                row["dof"], cov.pixel_sigma, row["points"])
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("network", type=Path)
    parser.add_argument("--run", default="fixed")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--inflation", type=float, default=None)
    parser.add_argument("--first-frame-only", action="store_true",
                        help="deregister every frame but each rig's frame0000 before adjusting (a one-frame network)")
    parser.add_argument("--track-test", action="store_true",
                        help="remove the tracks inconsistent_tracks finds (no truth) in a first adjustment")
    parser.add_argument("--track-quantile", type=float, default=0.999)
    parser.add_argument("--keep-noise", action="store_true",
                        help="--track-test: the second adjustment weighted by the first's (every track's) pixel "
                             "noise, not re-estimated without the removed tracks")
    parser.add_argument("--influence", action="store_true",
                        help="score every track's influence on the refined calibration (track_influence, no truth) "
                             "in a first default adjustment, and rank the truth's person and contour tracks by it")
    parser.add_argument("--influence-score", default="cook_calibration",
                        help="--influence: the score whose top tracks --influence-drop removes")
    parser.add_argument("--influence-drop", type=int, default=0,
                        help="--influence: remove this many top tracks, the noise held at the first adjustment's")
    parser.add_argument("--influence-threshold", type=float, default=None,
                        help="--influence: remove every track whose score is above this (instead of a count)")
    parser.add_argument("--influence-rounds", type=int, default=1,
                        help="--influence-threshold: adjust, score and remove again up to this many times in all")
    parser.add_argument("--influence-check", type=int, default=0,
                        help="--influence: delete each of this many top tracks alone, re-adjust (noise held) and "
                             "compare the refined calibration's change with the downdate's prediction")
    parser.add_argument("--influence-robust", action="store_true",
                        help="--influence: cook_calibration with the robust loss's weights at the solution "
                             "(rigsfm.run.adjustment.influence, the default adjustment's rule's score)")
    parser.add_argument("--influence-out", type=Path, default=None, help="--influence: the ranking (JSON)")
    parser.add_argument("--with-rule", action="store_true",
                        help="keep the default adjustment's own influential-track rule (adjust.MAX_TRACK_INFLUENCE); "
                             "off otherwise, so that every row is the adjustment of the tracks the options leave")
    parser.add_argument("--static-only", action="store_true",
                        help="remove every track that is not on a static surface (classify) before adjusting")
    parser.add_argument("--drop-classes", default=None,
                        help="comma-separated truth classes (person, contour, inconsistent) removed before adjusting")
    parser.add_argument("--track-min-observations", type=int, default=2,
                        help="--track-test judges only tracks of at least this many observations")
    parser.add_argument("--drop-random", type=int, nargs=2, default=None, metavar=("N", "SEED"),
                        help="remove N random tracks (a run-to-run noise floor for the track tests)")
    parser.add_argument("--drop-ids", type=Path, default=None,
                        help="a JSON list of 3D point ids of the mapping model, removed before adjusting")
    parser.add_argument("--loss", default=None, help="the adjustment's robust loss (rigsfm.run.options.Loss)")
    parser.add_argument("--pixel-sigma", type=float, default=None,
                        help="the refined adjustment's weighting noise held at this (px; not re-estimated)")
    parser.add_argument("--sensitivity-only", action="store_true")
    parser.add_argument("--bands-only", action="store_true")
    parser.add_argument("--explain", action="store_true", help="per pair: the band's J fed the true error")
    parser.add_argument("--draws", type=int, default=0, help="the band over this many fresh calibration draws")
    parser.add_argument("--refine", action="store_true", help="bands: the default adjustment (REFINE), not FIXED")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not args.with_rule:
        import rigsfm.run.adjustment.adjust as adjust_module

        adjust_module.MAX_TRACK_INFLUENCE = float("inf")
    if args.influence_check and args.influence_robust:
        parser.error("--influence-check compares the squared loss's downdate; drop --influence-robust")
    scene = args.network / "scene"
    options = scene_options(scene)
    truth = pycolmap.Reconstruction(str(scene / "ground_truth"))
    mapped = pycolmap.Reconstruction(str(args.network / args.run / "mapping"))
    if args.first_frame_only:
        for frame_id in list(mapped.reg_frame_ids()):
            if not frame_key(mapped, frame_id).endswith("frame0000.png"):
                mapped.deregister_frame(frame_id)
        for pid in list(mapped.point3D_ids()):
            if mapped.points3D[pid].track.length() < 2:
                mapped.delete_point3D(pid)
    given = load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml")
    exact = load_inputs(scene / "images", scene / "rigs_exact.yaml", scene / "scale.yaml")
    adjust_options = AdjustOptions()
    if args.loss is not None:
        adjust_options = replace(adjust_options, loss=args.loss)
    if args.inflation is not None:
        adjust_options = replace(adjust_options, pixel_sigma_inflation=args.inflation)
    if args.pixel_sigma is not None:
        hold_pixel_sigma(args.pixel_sigma)

    if args.explain:
        record = explain_pairs(mapped, truth, given, exact, adjust_options)
        if args.out:
            args.out.write_text(json.dumps(record, indent=1))
        return
    if args.track_test:
        calibration = Calibration.REFINE if args.refine else Calibration.FIXED
        first = adjust(pycolmap.Reconstruction(mapped), given.rigs, given.scale,
                       replace(adjust_options, calibration=calibration), given.priors)
        if args.keep_noise:
            logger.info("weighting noise held at the first adjustment's %.3f px", first.pixel_sigma)
            hold_pixel_sigma(first.pixel_sigma)
        bad = inconsistent_tracks(first.reconstruction, args.track_quantile, args.track_min_observations)
        classes = classify(mapped, truth, options)
        counts: dict[str, list[int]] = {}
        for pid, v in classes.items():
            row = counts.setdefault(v["class"], [0, 0])
            row[0] += 1
            row[1] += pid in bad
        logger.info("track test by the truth's class (tracks, removed): %s", counts)
        for pid in bad:
            if mapped.exists_point3D(pid):
                mapped.delete_point3D(pid)
    if args.influence:
        first = adjust(pycolmap.Reconstruction(mapped), given.rigs, given.scale,
                       replace(adjust_options, calibration=Calibration.REFINE), given.priors)
        logger.info("first adjustment: %s, held %s, noise %.3f px", first.calibration, sorted(first.held_rigs),
                    first.pixel_sigma)
        influence, linear = track_influence(first, with_deltas=True, robust=args.influence_robust)
        if args.influence_check:
            check_influence(mapped, given, adjust_options, first, influence, linear, args.influence_check)
            return
        classes = classify(mapped, truth, options)
        report = influence_report(influence, classes)
        report["held_rigs"] = sorted(first.held_rigs)
        if args.influence_out:
            report["per_track"] = {str(p): {**v, "class": classes[p]["class"]}
                                   for p, v in influence.items() if p in classes}
            args.influence_out.write_text(json.dumps(report, indent=1))
        if args.influence_drop or args.influence_threshold is not None:
            hold_pixel_sigma(first.pixel_sigma)
            if args.influence_threshold is not None:
                drop = [p for p, v in influence.items() if v[args.influence_score] > args.influence_threshold]
                by_class: dict[str, int] = {}
                for p in drop:
                    c = classes.get(p, {}).get("class", "-")
                    by_class[c] = by_class.get(c, 0) + 1
                logger.info("%s above %g: %d tracks, by the truth's class %s", args.influence_score,
                            args.influence_threshold, len(drop), by_class)
            else:
                drop = report["scores"][args.influence_score]["top_ids"][:args.influence_drop]
            for pid in drop:
                if mapped.exists_point3D(pid):
                    mapped.delete_point3D(pid)
            logger.info("removed the %d tracks of highest %s, noise held at %.3f px", len(drop),
                        args.influence_score, first.pixel_sigma)
            for round_ in range(2, args.influence_rounds + 1):
                if args.influence_threshold is None:
                    break
                again = adjust(pycolmap.Reconstruction(mapped), given.rigs, given.scale,
                               replace(adjust_options, calibration=Calibration.REFINE), given.priors)
                if again.calibration != Calibration.REFINE or again.held_rigs:
                    logger.info("round %d: rigs held (%s): no calibration to score", round_, sorted(again.held_rigs))
                    break
                influence = track_influence(again, robust=args.influence_robust)
                drop = [p for p, v in influence.items() if v[args.influence_score] > args.influence_threshold]
                by_class = {}
                for p in drop:
                    c = classes.get(p, {}).get("class", "-")
                    by_class[c] = by_class.get(c, 0) + 1
                logger.info("round %d: %s above %g: %d tracks, by the truth's class %s", round_,
                            args.influence_score, args.influence_threshold, len(drop), by_class)
                if not drop:
                    break
                for pid in drop:
                    mapped.delete_point3D(pid)
    if args.static_only:
        classes = classify(mapped, truth, options)
        for pid, v in classes.items():
            if v["class"] != "static":
                mapped.delete_point3D(pid)
        logger.info("kept %d static tracks, removed %d", mapped.num_points3D(), len(classes) - mapped.num_points3D())
    if args.drop_classes:
        drop = set(args.drop_classes.split(","))
        classes = classify(mapped, truth, options)
        for pid, v in classes.items():
            if v["class"] in drop:
                mapped.delete_point3D(pid)
        logger.info("kept %d static tracks, removed %d", mapped.num_points3D(), len(classes) - mapped.num_points3D())
    if args.drop_ids:
        for pid in json.loads(args.drop_ids.read_text()):
            if mapped.exists_point3D(pid):
                mapped.delete_point3D(pid)
    if args.drop_random:
        ids = sorted(mapped.point3D_ids())
        for pid in np.random.default_rng(args.drop_random[1]).choice(ids, args.drop_random[0], replace=False):
            mapped.delete_point3D(int(pid))
    if args.draws:
        record = draws_experiment(mapped, truth, given, exact, adjust_options, args.draws)
        if args.out:
            args.out.write_text(json.dumps(record, indent=1))
        return
    if args.bands_only:
        calibration = Calibration.REFINE if args.refine else Calibration.FIXED
        record = band_experiment(mapped, truth, given, replace(adjust_options, calibration=calibration), exact,
                                 floor=not args.refine)
        if args.out:
            args.out.write_text(json.dumps(record, indent=1))
        return
    if args.sensitivity_only:
        for unweighted in (False,):
            r = sensitivity_check(mapped, truth, given, exact, adjust_options, unweighted=unweighted)
            for k, v in r["frames"].items():
                print(f"  {k:28s} rot {v['actual_rotation_deg']:.4f} vs S dc {v['predicted_rotation_deg']:.4f} deg, "
                      f"t {v['actual_translation_mm']:.1f} vs {v['predicted_translation_mm']:.1f} mm; difference "
                      f"{v['rotation_difference_deg']:.4f} deg, {v['translation_difference_mm']:.1f} mm; distance from "
                      f"the gauge frame {v['radial_actual_mm']:+.1f} vs {v['radial_predicted_mm']:+.1f} mm")
        return
    classes = classify(mapped, truth, options)
    table = {}
    for cls in ("static", "person", "contour", "inconsistent"):
        res = np.concatenate([v["residuals"] for v in classes.values() if v["class"] == cls] or [np.zeros(0)])
        n = sum(1 for v in classes.values() if v["class"] == cls)
        table[cls] = {"tracks": n, "observations": int(res.size),
                      "residual_median_px": float(np.median(res)) if res.size else None,
                      "residual_p90_px": float(np.percentile(res, 90)) if res.size else None,
                      "residual_rms_px": float(np.sqrt(np.mean(res**2))) if res.size else None}
        logger.info("%-12s %5d tracks %6d obs: truth residual median %s p90 %s rms %s px", cls, n, res.size,
                    *(f"{table[cls][k]:.2f}" if table[cls][k] is not None else "-"
                      for k in ("residual_median_px", "residual_p90_px", "residual_rms_px")))
    person = frozenset(p for p, v in classes.items() if v["class"] == "person")
    contour = frozenset(p for p, v in classes.items() if v["class"] == "contour")
    bad = frozenset(p for p, v in classes.items() if v["class"] != "static")
    rows = [
        experiment(mapped, truth, given, adjust_options, "rigs.yaml, consider covariance"),
        experiment(mapped, truth, exact, adjust_options, "exact calibration, image-only covariance", image_only=True),
        experiment(mapped, truth, exact, adjust_options, "exact, person tracks removed", person, image_only=True),
        experiment(mapped, truth, exact, adjust_options, "exact, contour tracks removed", contour, image_only=True),
        experiment(mapped, truth, exact, adjust_options, "exact, only static tracks", bad, image_only=True),
        experiment(mapped, truth, given, adjust_options, "rigs.yaml, only static tracks", bad),
    ]
    record = {"network": args.network.name, "run": args.run, "classes": table, "experiments": rows}
    if args.out:
        args.out.write_text(json.dumps(record, indent=1))
    for r in rows:
        print(f"{r['label']:45s} chi2/dof {r['chi2_over_dof']:7.2f} ({r['dof']} dof, {r['points']} points, "
              f"weight sigma {r['weight_sigma_px']:.3f} px)")


if __name__ == "__main__":
    main()
