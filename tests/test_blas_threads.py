"""rigsfm.core.blas_threads: OpenBLAS on one thread for the narrow stage (its second adjustment included)."""

import numpy as np
import scipy.linalg  # noqa: F401  # scipy's own OpenBLAS, loaded

from rigsfm.core.blas_threads import _loaded_openblas, one_blas_thread
from rigsfm.run.narrow import stage


def _threads() -> list[int]:
    return [get() for get, _ in _loaded_openblas()]


def _two_threads() -> None:
    for _, set_ in _loaded_openblas():
        set_(2)


def test_every_loaded_openblas_runs_on_one_thread_inside_the_block_and_as_before_after():
    assert len(_loaded_openblas()) >= 2  # numpy's and scipy's
    _two_threads()
    with one_blas_thread():
        assert _threads() == [1] * len(_threads())
        assert np.allclose(np.linalg.cholesky(np.eye(3) * 4.0), np.eye(3) * 2.0)
    assert _threads() == [2] * len(_threads())


def test_the_second_adjustment_runs_on_one_blas_thread(monkeypatch):
    seen = []
    monkeypatch.setattr(stage, "adjust", lambda *args, **kwargs: seen.append((_threads(), args, kwargs)) or "adjusted")
    _two_threads()
    assert stage.adjust_on_one_blas_thread(1, 2, point_sigmas={3: 1.5}) == "adjusted"
    assert seen == [([1] * len(_threads()), (1, 2), {"point_sigmas": {3: 1.5}})]
    assert _threads() == [2] * len(_threads())
