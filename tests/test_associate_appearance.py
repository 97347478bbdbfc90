"""The appearance cue of rigsfm associate: the greys of a detection's head and torso, on a rendered crowd."""

from __future__ import annotations

import numpy as np
from test_associate import _associate_two_frames, _detections, _pair_f1, _two_frames, crowd  # noqa: F401  (the rendered crowd and its run, once per session)

from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.appearance import estimate


def _auc(same: np.ndarray, other: np.ndarray) -> float:
    """The chance that a same-person pair scores above a different-persons pair."""
    ranks = np.argsort(np.argsort(np.concatenate([same, other])))
    return float((ranks[:len(same)].sum() - len(same) * (len(same) - 1) / 2) / (len(same) * len(other)))


def test_appearance_separates_same_person_from_different_persons(crowd):  # noqa: F811
    """The descriptors the association samples from the run's images tell a person's views from other persons':
    a model estimated on half the crowd's persons gives the other half's same-person pairs a positive log ratio
    and pairs of different persons a negative one. The model the association estimates itself (from its own
    confident persons, no truth; on 4 rigs many of them are wrong) still ranks the pairs better than chance."""
    dataset, out = crowd
    model, truth = _detections(dataset, out)
    assert model.images_root is not None, "the run's summary should say where its images are"
    frame = associate_frames(model, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0]
    assert frame.result.appearance is not None, "the association should estimate an appearance model from the images"
    descriptors = np.concatenate([v.descriptor for v in frame.views])
    person = np.concatenate([np.asarray(truth.person[v.name]) for v in frame.views])
    view_of = np.concatenate([np.full(len(v.xy), k) for k, v in enumerate(frame.views)])
    real = np.flatnonzero(person >= 0)
    ids = np.unique(person[real])
    groups = -np.ones((len(ids), len(frame.views)), dtype=np.int64)
    for g, p in enumerate(ids):
        rows = real[person[real] == p]
        groups[g, view_of[rows]] = rows
    groups = groups[np.sum(groups >= 0, axis=1) >= 2]
    learn, test = groups[0::2], groups[1::2]
    same_a, same_b = [], []
    for a in range(test.shape[1]):
        for b in range(a + 1, test.shape[1]):
            both = (test[:, a] >= 0) & (test[:, b] >= 0)
            same_a.extend(test[both, a])
            same_b.extend(test[both, b])
    rng = np.random.default_rng(0)
    a, b = rng.choice(real, 20000), rng.choice(real, 20000)
    different = (view_of[a] != view_of[b]) & (person[a] != person[b])
    a, b = a[different], b[different]
    assert len(same_a) > 100

    learned = estimate(descriptors, view_of, learn)
    assert learned is not None
    same = learned.log_ratio(descriptors[same_a], descriptors[same_b])
    other = learned.log_ratio(descriptors[a], descriptors[b])
    assert np.median(same) > 0.5 and np.median(other) < -0.5, (np.median(same), np.median(other))
    assert _auc(same, other) > 0.8, _auc(same, other)

    own = frame.result.appearance
    own_auc = _auc(own.log_ratio(descriptors[same_a], descriptors[same_b]), own.log_ratio(descriptors[a], descriptors[b]))
    assert own_auc > 0.65, own_auc


def test_an_image_changed_since_the_run_lends_no_appearance(tmp_path, caplog):
    """A new recording under the run's image names is not the run's: its pixels are not read for the cue."""
    import logging

    import cv2

    from rigsfm.associate.pipeline import RunModel, _run_image_grey
    from rigsfm.core.io import file_sha256

    name = "rig01/narrow/f0.png"
    path = tmp_path / name
    path.parent.mkdir(parents=True)
    cv2.imwrite(str(path), np.full((8, 8), 100, np.uint8))
    recorded = file_sha256(path)
    model = RunModel({}, {}, set(), None, images_root=tmp_path, image_sha256={name: recorded})
    assert _run_image_grey(model, name) is not None
    cv2.imwrite(str(path), np.full((8, 8), 200, np.uint8))  # another recording, same name
    with caplog.at_level(logging.WARNING):
        assert _run_image_grey(model, name) is None
    assert "changed since the run" in caplog.text
    assert _run_image_grey(RunModel({}, {}, set(), None, images_root=tmp_path), name) is not None  # nothing recorded


def test_a_carried_frame_takes_the_first_frame_s_appearance_model(crowd, tmp_path, monkeypatch):  # noqa: F811
    """The next frame of the same cameras is associated once, with the appearance model and head sizes the first
    frame estimated from its own persons (no association of its own to estimate another from), and finds the
    persons as well as the first frame does."""
    dataset, out = crowd
    root = load_run(out).images_root
    assert root is not None
    for name in sorted((root).rglob("frame0000.*")):  # the next frame shows the same pixels
        for frame in ("frame0000", "frame0001"):
            link = tmp_path / name.relative_to(root).with_stem(frame)
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(name)
    posed, points, truths, _ = _two_frames(dataset, out, images_root=tmp_path)
    frames, solves = _associate_two_frames(posed, points, monkeypatch)
    assert frames[0].result.appearance is not None, "the first frame should estimate an appearance model"
    assert sum("frame0001" in n for n in solves) == 1, solves
    assert frames[1].result.appearance is frames[0].result.appearance
    for before, view in zip(frames[0].views, frames[1].views):
        assert view.head_px == before.head_px and view.descriptor is not None and len(view.descriptor) == len(view.xy)
    # each frame's images are read for its own association only: a recording's frames do not keep them all
    assert all(view.grey is None for frame in frames for view in frame.views)
    f1 = [_pair_f1(frame, truth) for frame, truth in zip(frames, truths)]
    assert f1[0] > 0.25 and f1[1] > 0.8 * f1[0], f1


def test_the_median_grey_by_counts_is_numpy_s():
    """An image's median grey from its counts is np.median's to the bit: odd and even pixel counts (the mean of the
    two middle greys), one grey, a one-pixel image, stored bytes and their floats; greys that are not whole numbers
    (a fraction, a NaN, a negative) go to np.median itself."""
    from rigsfm.associate.appearance import median_grey

    rng = np.random.default_rng(3)
    images = [rng.integers(0, top, size).astype(np.float64) for top in (1, 2, 7, 256)
              for size in ((61, 47), (60, 47), (1, 1), (2, 1), (3, 3))]
    images += [images[3].astype(np.uint8), rng.integers(0, 60000, (30, 31)).astype(np.float64)]
    # stored bytes, odd and even counts (counted by OpenCV's histogram)
    images += [rng.integers(lo, 256, size).astype(np.uint8) for lo in (0, 250) for size in ((61, 47), (60, 47), (1, 1), (2, 1), (3, 3))]
    odd = rng.integers(0, 256, (20, 21)).astype(np.float64)
    images += [odd + 0.5, np.where(odd > 200, np.nan, odd), odd - 100.0]
    for grey in images:
        expected = float(np.median(grey))
        assert median_grey(grey) == expected or (np.isnan(expected) and np.isnan(median_grey(grey))), grey.shape


def test_the_boxes_of_stored_greys_sum_as_each_box_by_itself():
    """Detections' box means of stored bytes (OpenCV's integral image) are each box's own sum's to the bit (the
    float greys' path): boxes of several sizes, cut at every edge of the image."""
    from rigsfm.associate.appearance import _box_means

    rng = np.random.default_rng(4)
    grey = rng.integers(0, 256, (61, 83)).astype(np.uint8)
    centres = np.r_[rng.uniform(-10, 95, (300, 2)), [[0, 0], [82, 60], [-3, 30], [40, 64]]]
    for half in (1.0, 2.4, 5.5, 40.0):
        assert np.array_equal(_box_means(grey, centres, half), _box_means(grey.astype(np.float64), centres, half)), half
