"""Persons linked across a recording's frames (rigsfm.associate.trajectories): the walk estimated from the
recording, the links right, and each link's confidence as often right as it says."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
from test_associate_tracked import OPTIONS, _recording

from rigsfm.associate import associate_frames
from rigsfm.associate.trajectories import link_persons, tracks


def test_links_find_who_walked_where_and_say_how_sure_they_are():
    """A crowd of 3 persons per m^2 whose points are measured to 3 cm: walking 5 cm a frame nearly every link is sure
    and right; walking 40 cm (the crowd's spacing) the links are unsure; in between and at both ends each link's
    confidence is, on average, how often it is right, and the walk is found."""
    covariance = np.tile(np.diag([0.03 ** 2, 0.03 ** 2, 0.05 ** 2]), (300, 1, 1))
    said, right_share = {}, {}
    for walk in (0.05, 0.15, 0.4):
        confidences, rights, walks = [], [], []
        for seed in range(5):
            rng = np.random.default_rng(seed)
            heads = np.c_[rng.uniform(-5, 5, (300, 2)), rng.uniform(1.5, 1.9, 300)]
            order = rng.permutation(300)  # this frame's persons in another order than the frame before's
            moved = heads + np.c_[rng.normal(0.0, walk, (300, 2)), np.zeros(300)]
            before = heads + rng.normal(0.0, 0.03, heads.shape)
            after = moved[order] + rng.normal(0.0, 0.03, heads.shape)
            links = link_persons(before, covariance, after, covariance)
            linked = links.earlier >= 0
            confidences.append(links.confidence[linked])
            rights.append(links.earlier[linked] == order[linked])
            walks.append(links.walk_m)
        said[walk] = float(np.mean(np.concatenate(confidences)))
        right_share[walk] = float(np.mean(np.concatenate(rights)))
        assert abs(np.mean(walks) / walk - 1) < 0.15, (walk, walks)
    assert right_share[0.05] > 0.95 and said[0.05] > 0.95, (right_share, said)
    assert said[0.4] < 0.5, said
    for walk in said:
        assert abs(said[walk] - right_share[walk]) < 0.08, (walk, said[walk], right_share[walk])


def test_a_recording_keeps_its_persons_tracks_at_10_frames_a_second():
    """The tests' five-camera ring recorded at 10 frames a second (heads walking ~1.3 m/s): the persons found in two
    consecutive frames keep one track where they are one head, and the first link's walk is the heads' own."""
    rng = np.random.default_rng(7)
    heads = np.c_[rng.uniform(-4, 4, (150, 2)), rng.uniform(1.6, 1.9, 150)]
    heading = rng.uniform(0, 2 * np.pi, 150)
    step = 0.13 * np.c_[np.cos(heading), np.sin(heading), np.zeros(150)]
    frames = [heads + k * step for k in range(3)]
    model, detections, ids = _recording(frames, np.zeros((5, 2)), sigma_px=3.5)
    found = associate_frames(model, detections, dataclasses.replace(OPTIONS, detection_probability=None))

    def head_of(frame, truth) -> np.ndarray:  # each person's head where most of its detections are one
        out = []
        for row in frame.result.members:
            held = collections.Counter(truth[v][i] for v, i in enumerate(row) if i >= 0).most_common(1)[0]
            out.append(held[0] if 2 * held[1] > sum(row >= 0) else -1)
        return np.array(out)

    heads_of = [head_of(f, t) for f, t in zip(found, ids)]
    for k in (1, 2):
        a, b = heads_of[k - 1], heads_of[k]
        same_track = found[k].track[:, None] == found[k - 1].track[None]
        same_head = (b[:, None] == a[None]) & (b[:, None] >= 0)
        both = same_head.any(axis=1)  # this frame's persons whose head the frame before found too
        kept = (same_track & same_head).any(axis=1)
        assert kept[both].mean() > 0.85, (k, kept[both].mean())
        wrong = (same_track & ~same_head & (b[:, None] >= 0) & (a[None] >= 0)).any(axis=1)
        assert wrong.sum() <= 0.05 * same_track.any(axis=1).sum(), (k, wrong.sum())
    # the first link (no step known yet) finds the heads' walk: 13 cm a frame
    assert abs(found[1].links.walk_m / (0.13 / np.sqrt(2)) - 1) < 0.25, found[1].links.walk_m
    assert found[0].links is None and (found[0].track == np.arange(len(found[0].result.points))).all()


def test_tracks_number_a_recording_whose_frames_are_empty():
    empty = (np.zeros((0, 3)), np.zeros((0, 3, 3)))
    one = (np.array([[0.0, 0.0, 1.7]]), np.eye(3)[None] * 1e-4)
    ids, links = tracks([empty, one, empty, one])
    assert [t.tolist() for t in ids] == [[], [0], [], [1]]
    assert links[0] is None and all(link is not None and link.walk_m is None for link in links[1:])


def test_the_terminal_says_how_many_persons_go_on_and_when_the_tracks_break(tmp_path):
    import json

    from rigsfm.cli.associate import tracks_line

    def frame(name: str, persons) -> None:  # persons: (position, after, after_confidence)
        (tmp_path / name).mkdir()
        rows = [{"person": p, "position_m": list(at), "after": after, "after_confidence": c}
                for p, (at, after, c) in enumerate(persons)]
        (tmp_path / name / "persons.json").write_text(json.dumps({"frame": f"{name}.png", "persons": rows}))

    frame("f0", [((0.0, 0.0, 1.7), None, None), ((3.0, 0.0, 1.7), None, None), ((6.0, 0.0, 1.6), None, None)])
    assert tracks_line(tmp_path) is None  # one frame: nothing linked
    frame("f1", [((0.1, 0.0, 1.7), 0, 0.95), ((3.0, 0.3, 1.7), 1, 0.9), ((9.0, 0.0, 1.7), None, None),
                       ((6.0, 0.2, 1.6), 2, 0.4)])
    line = tracks_line(tmp_path)
    # two of four go on, by 0.1 and 0.3 m (the third's link is too unsure to carry its track)
    assert line.startswith("tracks: 50% of the later frames' persons go on") and "median step of 0.20 m" in line
    assert "most tracks break" not in line
    frame("f2", [((0.5, 0.5, 1.7), 0, 0.3), ((3.0, 3.0, 1.7), 1, 0.2)] + [((9.0, 9.0, 1.7), None, None)] * 4)
    line = tracks_line(tmp_path)
    assert "20% of" in line and "most tracks break" in line


def test_a_step_repeated_from_the_frame_before_links_walkers_that_position_alone_cannot():
    """Walkers stepping 40 cm a frame in a crowd of 3 per m^2 (beyond its spacing) keep their heading: given each
    one's step from the frame before, nearly every link is right where position alone gets under half; with a fifth
    of the steps wrong (a wrong link's) most still are, as each person may also have walked from where it stood."""
    covariance = np.tile(np.diag([0.03 ** 2, 0.03 ** 2, 0.05 ** 2]), (300, 1, 1))
    rights = {"alone": [], "steps": [], "a fifth wrong": []}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        heads = np.c_[rng.uniform(-5, 5, (300, 2)), rng.uniform(1.5, 1.9, 300)]
        heading = rng.uniform(0, 2 * np.pi, 300)
        step = 0.4 * np.c_[np.cos(heading), np.sin(heading)]
        turned = 0.4 * np.c_[np.cos(heading + rng.normal(0, 0.15, 300)), np.sin(heading + rng.normal(0, 0.15, 300))]
        before = heads + rng.normal(0.0, 0.03, heads.shape)
        order = rng.permutation(300)
        after = (heads + np.c_[turned, np.zeros(300)])[order] + rng.normal(0.0, 0.03, heads.shape)
        wrong = step.copy()
        mistaken = rng.random(300) < 0.2
        wrong[mistaken] = rng.normal(0.0, 0.4, (int(mistaken.sum()), 2))
        added = np.tile(np.eye(2) * 4 * 0.03 ** 2, (300, 1, 1))
        for name, velocity in (("alone", None), ("steps", step), ("a fifth wrong", wrong)):
            links = link_persons(before, covariance, after, covariance, velocity, None if velocity is None else added)
            linked = links.earlier >= 0
            rights[name].append(np.mean(links.earlier[linked] == order[linked]) * np.mean(linked))
    share = {name: float(np.mean(r)) for name, r in rights.items()}
    assert share["alone"] < 0.55 and share["steps"] > 0.93 and share["a fifth wrong"] > 0.75, share
