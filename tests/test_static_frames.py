"""Several frames of static rigs: a track between two frames of one rig has no baseline. A person who moved between
the frames, matched to itself, gives two rays from (nearly) one centre that meet only at the lens. The global mapper
put such a point micrometres in front of a wide camera of a crowd recording (8 static rigs, 3 frames), COLMAP's angle
filter kept it, and its Jacobian left the joint covariance not positive definite: no covariance, no bands, every rig's
calibration held untested."""

from pathlib import Path

import numpy as np
import pycolmap
from synthetic_db import make_network, perturbed_model

from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.adjustment.track_baseline import points_without_baseline
from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec


def _second_static_frame(rec: pycolmap.Reconstruction, rig: str, offset: np.ndarray) -> dict[str, int]:
    """A second frame of ``rig`` from its first frame's centre moved by ``offset``, its wide image observing the first
    frame's wide points at the same pixels (a static background renders alike in both frames) and with one keypoint
    more, at the end; its narrow image observes nothing. Returns the new images' ids by sensor."""
    first = rec.find_image_with_name(f"{rig}/wide/frame0000.png")
    frame = rec.frame(first.frame_id)
    pose = frame.rig_from_world
    centre = pose.inverse().translation + offset
    new_frame = pycolmap.Frame(frame_id=max(rec.frames) + 1, rig_id=frame.rig_id,
                               rig_from_world=pycolmap.Rigid3d(pose.rotation, -(pose.rotation * centre)))
    ids, images = {}, []
    for data_id in frame.data_ids:
        old = rec.image(data_id.id)
        sensor = old.name.split("/")[1]
        image = pycolmap.Image(image_id=max(rec.images) + 1 + len(ids), name=f"{rig}/{sensor}/frame0001.png",
                               camera_id=old.camera_id, frame_id=new_frame.frame_id)
        ids[sensor] = image.image_id
        new_frame.add_data_id(pycolmap.data_t(data_id.sensor_id, image.image_id))
        if sensor == "wide":
            image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p.xy) for p in old.points2D if p.has_point3D()]
                                                  + [pycolmap.Point2D(np.zeros(2))])
        images.append(image)
    rec.add_frame(new_frame)
    for image in images:
        rec.add_image(image)
    tracked = [p.point3D_id for p in first.points2D if p.has_point3D()]
    for k, point_id in enumerate(tracked):
        rec.add_observation(point_id, pycolmap.TrackElement(ids["wide"], k))
    return ids


def test_a_track_between_frames_of_a_static_rig_leaves_the_covariance_and_bands(tmp_path):
    net = make_network(tmp_path, num_rigs=3, seed=3)
    mapped = perturbed_model(net.ground_truth, seed=3)
    first = mapped.find_image_with_name("rig01/wide/frame0000.png")
    camera = mapped.cameras[first.camera_id]
    # The moving person, seen at the image centre in the first frame and 150 px to the right in the second: the rays
    # meet just in front of the first frame's lens, the second frame's centre a little behind it on its ray (the
    # mapper's estimate of a static rig's two frames differs by such a speck).
    pixels = np.array([[camera.width / 2, camera.height / 2], [camera.width / 2 + 150.0, camera.height / 2]])
    rays = first.cam_from_world().rotation.inverse() * np.c_[np.asarray(camera.cam_from_img(pixels)), np.ones(2)]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    xyz = first.projection_center() + 1e-8 * rays[0]
    ids = _second_static_frame(mapped, "rig01", xyz - 3e-7 * rays[1] - first.projection_center())
    second = mapped.image(ids["wide"])
    spare = next(k for k, p in enumerate(first.points2D) if p.has_point3D())  # one of its observations, reused
    mapped.delete_observation(first.image_id, spare)
    track = pycolmap.Track()
    for image, k, xy in ((first, spare, pixels[0]), (second, len(second.points2D) - 1, pixels[1])):
        assert np.allclose(np.asarray(camera.img_from_cam(image.cam_from_world() * xyz[None]))[0], xy, atol=1e-3)
        image.points2D[k].xy = xy
        track.add_element(image.image_id, k)
    collapsed = mapped.add_point3D(xyz, track, np.zeros(3, np.uint8))
    assert points_without_baseline(mapped) == [collapsed]

    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    truth = net.ground_truth
    metres = float(np.linalg.norm(truth.find_image_with_name(a).projection_center()
                                  - truth.find_image_with_name(b).projection_center()))
    result = adjust(mapped, net.rigs, ScaleSpec(Path(tmp_path / "scale.yaml"), (CameraDistance(a, b, metres),), ()))
    assert not result.reconstruction.exists_point3D(collapsed)
    assert result.reconstruction.image(ids["wide"]).num_points3D > 0.9 * first.num_points3D - 1
    uncertainty = estimate_uncertainty(result)
    assert uncertainty.covariance is not None
    assert uncertainty.bands  # every narrow pair with a shared view, the second frame's included
    assert any("frame0001" in i or "frame0001" in j for i, j in uncertainty.bands)
