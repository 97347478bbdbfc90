"""The appearance cue of rigsfm associate: the greys of a detection's head and torso, on a rendered crowd."""

from __future__ import annotations

import numpy as np
from test_associate import _detections, crowd  # noqa: F401  (the rendered crowd and its run, once per session)

from rigsfm.associate import AssociateOptions, associate_frames, from_arrays
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
