"""A detection's ray between the two heights, seen from a camera across the crowd (rigsfm.associate.segments)."""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.associate import AssociateOptions
from rigsfm.associate.segments import segment_in_view
from rigsfm.associate.solve import View, _Frame

F, W, H = 1800.0, 812, 617


def _view(name: str, centre: np.ndarray, target: np.ndarray, heads: np.ndarray) -> View:
    """A pinhole narrow camera at ``centre`` aimed at ``target``, detecting ``heads`` exactly."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    r = np.stack([right, np.cross(forward, right), forward])
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])
    k = np.asarray(camera.calibration_matrix())
    view = View(name, k, r, -r @ centre, centre, W, H, camera, np.zeros((0, 2)))
    view.xy, _ = view.project(heads)
    return view


def _facing_pair(head: np.ndarray) -> tuple[View, View]:
    # two rigs 18 m apart across the crowd, cameras 3.5 m up, both aimed at one head 13 m from the first: that
    # camera's ray through the head reaches 1.0 m of height ~19 m away, behind the camera opposite
    a = _view("a", np.array([0.0, 0.0, 3.5]), head, head[None])
    b = _view("b", np.array([18.0, 0.0, 3.5]), head, head[None])
    return a, b


def test_a_segment_passing_behind_the_camera_opposite_keeps_its_front_part():
    head = np.array([13.0, 0.0, 1.8])
    a, b = _facing_pair(head)
    ray = head - a.centre
    low = a.centre + ray * (1.0 - a.centre[2]) / ray[2]
    high = a.centre + ray * (2.1 - a.centre[2]) / ray[2]
    assert b.project(low[None])[1][0] < 0 < b.project(high[None])[1][0]  # the far end lies behind b
    start, end, ok = segment_in_view(b, low[None], high[None])
    assert ok[0]
    # b's detection of the head lies on the segment's image, between its ends
    seen = b.xy[0]
    along = np.dot(seen - start[0], end[0] - start[0]) / np.sum((end[0] - start[0]) ** 2)
    normal = np.array([-(end[0] - start[0])[1], (end[0] - start[0])[0]]) / np.linalg.norm(end[0] - start[0])
    assert 0.0 < along < 1.0 and abs(np.dot(seen - start[0], normal)) < 1e-6
    # a segment wholly behind the camera has no image
    behind = np.array([[19.0, 0.0, 1.5]]), np.array([[25.0, 0.0, 1.5]])
    assert not segment_in_view(b, *behind)[2][0]


def test_the_head_between_two_facing_cameras_is_a_candidate_pair():
    head = np.array([13.0, 0.0, 1.8])
    a, b = _facing_pair(head)
    seeds = _Frame([a, b], AssociateOptions(pixel_sigma=1.5)).pair_candidates()
    assert [0, 1] in seeds.tolist()
