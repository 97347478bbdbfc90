"""The sanity checks catch what reprojection errors hide."""

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from synthetic_db import make_network

from rigsfm.core.errors import InputError, ReconstructionError
from rigsfm.core.workspace import Workspace
from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.adjustment.scale import Measurement, ScaleEstimate, estimate_scale
from rigsfm.run.checks.diagnostics import check_reconstruction, contradicted_pairs
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.mapping.mapper import run_mapping
from rigsfm.run.mapping.ties import loosely_tied_rigs
from rigsfm.run.options import MappingOptions


def test_a_rigid_network_passes(tmp_path):
    net = make_network(tmp_path, num_rigs=4, seed=5)
    mapped = run_mapping(Workspace(tmp_path), tmp_path, MappingOptions(), num_wide=4).reconstruction
    result = adjust(mapped, net.rigs, None)
    assert loosely_tied_rigs(result.reconstruction) == []


def test_rigs_held_by_two_view_tracks_only_are_flagged(tmp_path):
    net = make_network(tmp_path, num_rigs=4, seed=5)
    rec = net.ground_truth
    # Keep each point in two images only: every track becomes a two-view track.
    for point3D_id in list(rec.point3D_ids()):
        elements = [(e.image_id, e.point2D_idx) for e in rec.points3D[point3D_id].track.elements]
        for image_id, point2D_idx in elements[2:]:
            rec.delete_observation(image_id, point2D_idx)
    assert max(p.track.length() for p in rec.points3D.values()) == 2
    assert loosely_tied_rigs(rec) == ["rig01", "rig02", "rig03", "rig04"]
    assert any(w.startswith("SHAPE NOT DETERMINED") for w in check_reconstruction(rec, None))


def test_disagreeing_scale_measurements_are_flagged():
    scale = ScaleEstimate(1.0, 0.001, (Measurement("camera_distance", "a - b", 30.0, 30.0, 0.01),
                                      Measurement("known_length", "bar", 2.0, 2.6, 0.002, 0.01)))
    warnings = check_reconstruction(_empty(), scale)
    assert len(warnings) == 1 and "SCALE MEASUREMENTS DISAGREE: bar" in warnings[0] and "+30.00 %" in warnings[0]
    agreeing = ScaleEstimate(1.0, 0.001, (Measurement("camera_distance", "a - b", 30.0, 30.0, 0.01),
                                          Measurement("known_length", "bar", 2.0, 2.01, 0.002, 0.01)))
    assert check_reconstruction(_empty(), agreeing) == []


def _empty():
    return pycolmap.Reconstruction()


def test_measurements_naming_unregistered_cameras_are_left_out_and_reported(tmp_path):
    rec = make_network(tmp_path, num_rigs=3, seed=2).ground_truth
    centre = {name: rec.find_image_with_name(f"{name}/wide/frame0000.png").projection_center()
              for name in ("rig01", "rig02")}
    true = float(np.linalg.norm(centre["rig01"] - centre["rig02"]))
    spec = ScaleSpec(Path("scale.yaml"), (CameraDistance("rig01/wide", "rig02/wide", 2.0 * true),
                                          CameraDistance("rig01/wide", "rig09/wide", 30.0)), ())
    scale = estimate_scale(rec, spec)
    assert scale.metres_per_unit == pytest.approx(2.0) and len(scale.measurements) == 1
    assert scale.unused == ("rig01/wide - rig09/wide: rig09/wide was not registered",)
    (warning,) = check_reconstruction(_empty(), scale)
    assert warning.startswith("SCALE MEASUREMENT UNUSED: rig01/wide - rig09/wide: rig09/wide was not registered")
    only_unusable = ScaleSpec(Path("scale.yaml"), spec.camera_distances[1:], ())
    with pytest.raises(ReconstructionError, match="no measurement of scale.yaml can set the scale: .*rig09/wide"):
        estimate_scale(rec, only_unusable)


def test_a_rig_moved_off_its_verified_matches_is_flagged(tmp_path):
    net = make_network(tmp_path, num_rigs=4, seed=5)
    rec = net.ground_truth
    assert contradicted_pairs(net.database, rec) == []
    # Slide rig03 sideways by a tenth of the network's size: its rotations stay exact, its matches no longer fit.
    centres = np.array([image.projection_center() for image in rec.images.values()])
    frame = next(rec.frames[image.frame_id] for image in rec.images.values() if image.name.startswith("rig03/"))
    shift = 0.1 * np.ptp(centres, axis=0).max()
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation,
                                            frame.rig_from_world.translation + np.array([shift, 0.0, 0.0]))
    rows = contradicted_pairs(net.database, rec)
    assert [row.split(":")[0] for row in rows] == ["rig01-rig03", "rig02-rig03", "rig03-rig04"]
    assert all(float(row.split("median error ")[1].split(" px")[0]) > 10.0 for row in rows)
    (warning,) = [w for w in check_reconstruction(rec, None, net.database) if w.startswith("MATCHES CONTRADICT")]
    assert "rig02-rig03" in warning


def test_scale_messages_name_the_measurement_and_why(tmp_path):
    """A zero model length names its measurement; a known length says which of its images were not registered."""
    from rigsfm.run.inputs.scale_file import KnownLength, LengthObservation

    rec = make_network(tmp_path, num_rigs=3, seed=2).ground_truth
    same = CameraDistance("rig01/wide", "rig01/wide/frame0000.png", 1.0)  # validation refuses it; scale.py names it
    with pytest.raises(ReconstructionError, match=r"scale measurement\(s\) rig01/wide - rig01/wide/frame0000.png of "
                                                  r"scale.yaml have zero length in the model"):
        estimate_scale(rec, ScaleSpec(Path("scale.yaml"), (same,), ()))
    images = [rec.find_image_with_name(f"rig0{k}/wide/frame0000.png") for k in (1, 2)]
    point = next(iter(rec.points3D.values())).xyz
    xy = [np.asarray(rec.cameras[im.camera_id].img_from_cam(np.asarray(im.cam_from_world() * point)[None]))[0]
          for im in images]
    bar = KnownLength(2.0, (LengthObservation(images[0].name, tuple(xy[0]), tuple(xy[0] + 30)),
                            LengthObservation("rig09/wide/frame0000.png", (1.0, 1.0), (5.0, 5.0))))
    distance = CameraDistance("rig01/wide", "rig02/wide", 10.0)
    scale = estimate_scale(rec, ScaleSpec(Path("scale.yaml"), (distance,), (bar,)))
    assert scale.unused == ("known_length[0] (2.0 m): fewer than two of its images were registered "
                            "(rig09/wide/frame0000.png not)",)
    assert [m.label for m in scale.measurements] == ["rig01/wide - rig02/wide"]


def _distances(rec, pairs, factors, sensors=("wide", "wide")) -> ScaleSpec:
    """Camera distances between rigs ``pairs`` of ``rec`` (metres = model units), each times its factor."""
    def centre(rig):
        return rec.find_image_with_name(f"{rig}/wide/frame0000.png").projection_center()

    return ScaleSpec(Path("scale.yaml"), tuple(
        CameraDistance(f"{a}/{sensors[0]}", f"{b}/{sensors[1]}", factor * float(np.linalg.norm(centre(a) - centre(b))))
        for (a, b), factor in zip(pairs, factors, strict=True)), ())


def test_a_distance_in_other_units_is_named_before_the_adjustment(tmp_path):
    """Measurements imply one scale of the mapped model: one 1000x off (millimetres written as metres) is named with
    the distance the others give; it made the adjustment and the uncertainty stage take minutes."""
    from rigsfm.run.adjustment.scale_check import check_scale_agreement

    net = make_network(tmp_path, num_rigs=4, seed=5)
    rec = net.ground_truth
    pairs = (("rig01", "rig02"), ("rig02", "rig03"), ("rig03", "rig04"))
    check_scale_agreement(rec, _distances(rec, pairs, (2.0, 2.0, 2.0)), net.rigs)  # the model in other units: fine
    check_scale_agreement(rec, _distances(rec, pairs, (2.0, 2.6, 1.7)), net.rigs)  # the mapper's shape: fine
    # narrow ends: their centres lie a baseline from the wide ones the mapped model holds
    check_scale_agreement(rec, _distances(rec, pairs, (1.0, 1.0, 1.0), ("narrow", "wide")), net.rigs)
    spec = _distances(rec, pairs, (1.0, 1000.0, 1.0))
    with pytest.raises(InputError, match=r"^scale.yaml: camera_distance\[1\] \('rig02/wide' - 'rig03/wide', [\d.]+ m\) "
                                         r"is 1000x what the other 2 measurement\(s\) give in the mapped model "
                                         r"\([\d.]+ m\): a unit mistake .* Give it in metres"):
        check_scale_agreement(rec, spec, net.rigs)
    with pytest.raises(InputError, match=r"camera_distance\[0\] .*is 1/3.3 what the other 2"):  # feet
        check_scale_agreement(rec, _distances(rec, pairs, (1 / 3.28, 1.0, 1.0)), net.rigs)
    with pytest.raises(InputError, match=r"^scale.yaml: camera_distance\[0\] \(.*\) and camera_distance\[1\] \(.*\) "
                                         r"disagree on the scale by 1/1000 in the mapped model"):
        check_scale_agreement(rec, _distances(rec, pairs[:2], (1.0, 1000.0)), net.rigs)
    check_scale_agreement(rec, _distances(rec, pairs[:1], (1000.0,)), net.rigs)  # alone, it is the scale
    # Two that disagree by less than a unit mistake: the model may be the wrong one (a pair registered from weak
    # matches), so the adjustment reports it instead of a refusal blaming the units.
    check_scale_agreement(rec, _distances(rec, pairs[:2], (1.0, 2.5)), net.rigs)


def test_a_network_of_implausible_size_is_flagged(tmp_path):
    """A length given in centimetres for metres (or millimetres) scales the network to hundreds of kilometres (or
    millimetres): the run says so instead of delivering it silently."""
    rec = make_network(tmp_path, num_rigs=3, seed=2).ground_truth
    centres = np.array([im.projection_center() for im in rec.images.values()])
    span = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0)))  # the check's span: the box's diagonal
    scale = ScaleEstimate(1.0, 0.001, (Measurement("camera_distance", "a - b", 30.0, 30.0, 0.01),))
    for factor, expected in ((20.0 / span, None), (6e5 / span, "600 km"), (0.005 / span, "5 mm")):
        scaled = pycolmap.Reconstruction(rec)
        scaled.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
        flagged = [w for w in check_reconstruction(scaled, scale) if w.startswith("IMPLAUSIBLE SCALE")]
        assert (flagged == []) if expected is None else (len(flagged) == 1 and expected in flagged[0]), flagged
    assert not [w for w in check_reconstruction(rec, None) if w.startswith("IMPLAUSIBLE")]  # not metric: not judged
