"""A track's influence on the refined calibration (``rigsfm.run.adjustment.influence``) and the rule that removes the
tracks that pull it before the hold-or-refine test (``adjust.MAX_TRACK_INFLUENCE``), on a small network built here:
three rigs whose wide images see a box of points, rig02's outer image seen only by a few wrong two-view matches (as a
crowd's matches across walking bodies: each fits after adjustment, the calibration bent to it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from synthetic_world import add_hybrid_rig, look_at

import rigsfm.run.adjustment.adjust as adjust_module
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.adjustment.influence import track_influence
from rigsfm.run.adjustment.priors import BoardDefaults, calibration_priors
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.options import AdjustOptions, Calibration

WIDTH, HEIGHT = 1024, 768
WIDE = [500.0, 500.0, 512.0, 384.0, -0.05, 0.01, 0.0, 0.0]
NARROW = [2000.0, 2000.0, 512.0, 384.0, 0.0, 0.0, 0.0, 0.0]
INNER_PX = 260.0  # rig02's good observations stay within this radius of its image centre
OUTER_PX = 330.0  # the wrong matches lie beyond it
NOISE_PX = 0.1  # the static observations' noise: the weighting noise is small beside a wrong match's misfit


def _network(root: Path, wrong: int, shift_px: float = 2.0, seed: int = 0, num_rigs: int = 3):
    """``num_rigs`` (2 or 3) rigs on a 60 deg arc, 15 m from a 16 x 16 x 4 m box of points, every point seen by the three wide images with
    ``NOISE_PX`` noise, except that rig02 sees only its inner image; then ``wrong`` two-view tracks rig01-rig02 in rig02's
    outer image, rig02's keypoint moved ``shift_px`` across its epipolar line, outwards. Returns ``(rigs, model,
    scale spec, priors, the wrong tracks' point ids)``; the model starts at the truth's poses moved slightly."""
    rng = np.random.default_rng(seed)
    rigs, poses = [], []
    for index, angle in enumerate(np.radians([-30.0, 0.0, 30.0][:num_rigs]), start=1):
        centre = np.array([15.0 * np.cos(angle), 15.0 * np.sin(angle), 3.5])
        rigs.append(RigCalibration(f"rig{index:02d}", pycolmap.Camera(model="OPENCV", width=WIDTH, height=HEIGHT,
                                                                        params=WIDE),
                                   pycolmap.Camera(model="OPENCV", width=WIDTH, height=HEIGHT, params=NARROW),
                                   pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.05, 0.0, 0.0])),
                                                    np.array([-0.06, 0.0, 0.0]))))
        poses.append(look_at(centre, np.array([0.0, 0.0, 1.0])))
    camera = rigs[0].wide
    centre_px = np.array(WIDE[2:4])

    def project(pose: pycolmap.Rigid3d, xyz: np.ndarray) -> np.ndarray | None:
        local = np.asarray(pose * xyz[None])[0]
        if local[2] <= 0.1:
            return None
        xy = np.asarray(camera.img_from_cam(local[None]))[0]
        return xy if 5 <= xy[0] <= WIDTH - 5 and 5 <= xy[1] <= HEIGHT - 5 else None

    observations: dict[int, list] = {rig: [] for rig in range(1, num_rigs + 1)}  # rig -> [(point index, xy)]
    points: list[np.ndarray] = []
    wrong_ids: list[int] = []
    while len(points) < 600:  # static points: every rig's view, rig02's only in its inner image
        xyz = rng.uniform([-8.0, -8.0, 0.0], [8.0, 8.0, 4.0])
        xy = [project(pose, xyz) for pose in poses]
        if any(x is None for x in xy):
            continue
        k = len(points)
        points.append(xyz)
        for rig, x in enumerate(xy, start=1):
            if rig != 2 or np.linalg.norm(x - centre_px) < INNER_PX:
                observations[rig].append((k, x + rng.normal(0.0, NOISE_PX, 2)))
    while len(wrong_ids) < wrong:
        xyz = rng.uniform([-10.0, -10.0, 0.0], [10.0, 10.0, 6.0])
        xa, xb = project(poses[0], xyz), project(poses[1], xyz)
        if xa is None or xb is None or np.linalg.norm(xb - centre_px) < OUTER_PX:
            continue
        # the epipolar line of xa in rig02's image: the point slid along its ray in rig01
        ray = np.asarray(poses[0] * xyz[None])[0]
        near, far = (project(poses[1], np.asarray(poses[0].inverse() * (ray * f)[None])[0]) for f in (0.95, 1.05))
        if near is None or far is None:
            continue
        along = (far - near) / np.linalg.norm(far - near)
        across = np.array([-along[1], along[0]])
        across *= np.sign(across @ (xb - centre_px)) or 1.0
        k = len(points)
        points.append(xyz)
        wrong_ids.append(k)
        observations[1].append((k, xa + rng.normal(0.0, NOISE_PX, 2)))
        observations[2].append((k, xb + shift_px * across))

    rec = pycolmap.Reconstruction()
    image_of: dict[int, int] = {}
    for index, (rig, pose) in enumerate(zip(rigs, poses), start=1):
        wide = pycolmap.Camera(camera_id=2 * index - 1, model="OPENCV", width=WIDTH, height=HEIGHT, params=WIDE)
        narrow = pycolmap.Camera(camera_id=2 * index, model="OPENCV", width=WIDTH, height=HEIGHT, params=NARROW)
        moved = pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(0.0, 1e-3, 3)) * pose.rotation,
                                 np.asarray(pose.translation) + rng.normal(0.0, 0.01, 3))
        images = add_hybrid_rig(rec, index, rig.name, wide, narrow, rig.narrow_from_wide, moved,
                                {"wide": [xy for _, xy in observations[index]]})
        image_of[index] = images[0].image_id
    tracks: dict[int, pycolmap.Track] = {}
    for rig, rows in observations.items():
        for point2d, (k, _) in enumerate(rows):
            tracks.setdefault(k, pycolmap.Track()).add_element(image_of[rig], point2d)
    point_id = {k: rec.add_point3D(points[k] + rng.normal(0.0, 0.01, 3), tracks[k], np.zeros(3, np.uint8))
                for k in sorted(tracks) if tracks[k].length() > 1}  # two rigs: rig02 sees only its inner image
    a, b = (f"{rigs[k].name}/wide/frame0000.png" for k in (0, -1))
    metres = float(np.linalg.norm(poses[0].inverse().translation - poses[-1].inverse().translation))
    spec = ScaleSpec(root / "scale.yaml", (CameraDistance(a, b, metres),), ())
    # A loose distortion prior, as from a board that did not reach the image corners: the images must inform it.
    priors = calibration_priors(rigs, defaults=BoardDefaults(radial=(0.02, 0.01, 0.001)))
    return rigs, rec, spec, priors, [point_id[k] for k in wrong_ids]


def _wide_error(result, rig: RigCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The refined wide camera's error against rigs.yaml's (here the truth) and its posterior sigma."""
    rec = result.reconstruction
    camera_id = rec.find_image_with_name(f"{rig.name}/wide/frame0000.png").camera_id
    return np.asarray(rec.cameras[camera_id].params) - rig.wide.params, result.covariance.sigma(("camera", camera_id))


def test_wrong_two_view_tracks_that_bend_the_calibration_are_removed(tmp_path, monkeypatch):
    """Six wrong matches are all that sees rig02's outer image: refined with them, its distortion follows them more
    than 3 posterior sigma from the truth (rigs.yaml is exact here). The two that pull most score above
    MAX_TRACK_INFLUENCE, every static track far below; the rule removes those two (the four others then pull less
    than the threshold each, and stay), and the refined calibration is back within one sigma."""
    rigs, mapped, spec, priors, wrong = _network(tmp_path, wrong=6)
    monkeypatch.setattr(adjust_module, "MAX_TRACK_INFLUENCE", float("inf"))  # the rule off
    bent = adjust(mapped, rigs, spec, priors=priors)
    monkeypatch.undo()
    assert bent.calibration == Calibration.REFINE and not bent.held_rigs
    error, sigma = _wide_error(bent, rigs[1])
    assert np.max(np.abs(error) / np.where(sigma > 0, sigma, np.inf)) > 3.0, (error, sigma)
    scores = track_influence(bent)
    pulling = {pid for pid, score in scores.items() if score > adjust_module.MAX_TRACK_INFLUENCE}
    assert pulling and pulling <= set(wrong)
    assert max(score for pid, score in scores.items() if pid not in wrong) < adjust_module.MAX_TRACK_INFLUENCE / 10

    result = adjust(mapped, rigs, spec, priors=priors)
    assert result.calibration == Calibration.REFINE and not result.held_rigs
    influential = result.influential
    assert influential is not None and influential.removed == sum(influential.per_round) >= len(pulling)
    removed = {pid for pid in bent.reconstruction.point3D_ids() if not result.reconstruction.exists_point3D(pid)}
    assert len(removed) == influential.removed and removed <= set(wrong)
    error, sigma = _wide_error(result, rigs[1])
    assert np.all(np.abs(error) <= sigma + 1e-12), (error, sigma)


def test_without_pulling_tracks_the_adjustment_is_unchanged(tmp_path, monkeypatch):
    """The same network without the wrong matches: nothing scores above the threshold, nothing is removed, and the
    result is the adjustment without the rule to the last digit."""
    rigs, mapped, spec, priors, _ = _network(tmp_path, wrong=0)
    result = adjust(mapped, rigs, spec, priors=priors)
    assert result.influential is not None and result.influential.removed == 0 and result.influential.rounds == 1
    assert result.influential.largest_kept < adjust_module.MAX_TRACK_INFLUENCE
    monkeypatch.setattr(adjust_module, "MAX_TRACK_INFLUENCE", float("inf"))
    plain = adjust(mapped, rigs, spec, priors=priors)
    assert result.reconstruction.num_points3D() == plain.reconstruction.num_points3D() == mapped.num_points3D()
    for camera_id, camera in plain.reconstruction.cameras.items():
        np.testing.assert_array_equal(result.reconstruction.cameras[camera_id].params, camera.params)
    for frame_id in plain.reconstruction.reg_frame_ids():
        np.testing.assert_array_equal(result.reconstruction.frame(frame_id).rig_from_world.matrix(),
                                      plain.reconstruction.frame(frame_id).rig_from_world.matrix())


@pytest.mark.parametrize("held", [frozenset(), frozenset({"rig02"})])
def test_the_sampled_band_draws_and_held_rigs_are_not_scored(tmp_path, held):
    """``held_rigs`` given (the sampled band's draws repeat the estimate's choice): no track is scored or removed."""
    rigs, mapped, spec, priors, wrong = _network(tmp_path, wrong=6)
    result = adjust(mapped, rigs, spec, priors=priors, held_rigs=held, with_covariance=False)
    assert result.influential is None
    assert all(result.reconstruction.exists_point3D(pid) for pid in wrong)


def test_a_network_the_test_holds_is_not_scored(tmp_path):
    """With priors far tighter than the images can inform (a hundredth of a good board's sigmas), the hold-or-refine
    test holds every rig on the first pass, and the rule does not run (it may hold what the test refined, never refine
    what it held): --fixed-calibration's adjustment of every track, the wrong ones included."""
    rigs, mapped, spec, _, wrong = _network(tmp_path, wrong=6)
    tight = BoardDefaults(focal_relative=1.2e-5, principal_point_px=0.006, radial=(5e-6, 3e-6, 1e-6), tangential=1e-7,
                          rotation_deg=4.5e-4, translation_m=6e-6)
    result = adjust(mapped, rigs, spec, priors=calibration_priors(rigs, defaults=tight))
    assert result.calibration == Calibration.FIXED and all(d.held for d in result.decisions)
    assert result.influential is None
    assert all(result.reconstruction.exists_point3D(pid) for pid in wrong)


def test_a_two_rig_network_is_held_though_the_images_inform_it(tmp_path):
    """Two rigs whose images inform their calibration (over nine-tenths of a direction's prior variance removed, and
    a refinement the consistency test passes): the network is too small to be refined, so the adjustment is
    --fixed-calibration's, pose for pose."""
    rigs, mapped, spec, priors, _ = _network(tmp_path, wrong=0, num_rigs=2)
    result = adjust(mapped, rigs, spec, priors=priors)
    assert [d.held for d in result.decisions] == [True, True]
    assert all("a network of 2 rigs" in d.reason for d in result.decisions)
    assert max(d.largest_gain for d in result.decisions) > 0.9  # informed: the size alone holds them
    fixed = adjust(mapped, rigs, spec, AdjustOptions(calibration=Calibration.FIXED), priors=priors)
    assert result.calibration == Calibration.FIXED
    for frame_id in fixed.reconstruction.reg_frame_ids():
        np.testing.assert_allclose(result.reconstruction.frame(frame_id).rig_from_world.matrix(),
                                   fixed.reconstruction.frame(frame_id).rig_from_world.matrix(), atol=1e-9)
