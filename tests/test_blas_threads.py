"""rigsfm.core.blas_threads: BLAS on one thread for the narrow stage (its second adjustment included)."""

import numpy as np
import scipy.linalg  # noqa: F401  # scipy's own OpenBLAS, loaded
from threadpoolctl import threadpool_info, threadpool_limits

from rigsfm.core.blas_threads import one_blas_thread
from rigsfm.run.narrow import stage


def _threads() -> list[int]:
    return [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]


def test_every_loaded_blas_runs_on_one_thread_inside_the_block_and_as_before_after():
    with threadpool_limits(limits=2, user_api="blas"):
        assert len(_threads()) >= 2  # numpy's and scipy's
        assert _threads() == [2] * len(_threads())
        with one_blas_thread():
            assert _threads() == [1] * len(_threads())
            assert np.allclose(np.linalg.cholesky(np.eye(3) * 4.0), np.eye(3) * 2.0)
        assert _threads() == [2] * len(_threads())


def test_the_second_adjustment_runs_on_one_blas_thread(monkeypatch):
    seen = []
    monkeypatch.setattr(stage, "adjust", lambda *args, **kwargs: seen.append((_threads(), args, kwargs)) or "adjusted")
    with threadpool_limits(limits=2, user_api="blas"):
        assert stage.adjust_on_one_blas_thread(1, 2, point_sigmas={3: 1.5}) == "adjusted"
        assert seen == [([1] * len(_threads()), (1, 2), {"point_sigmas": {3: 1.5}})]
        assert _threads() == [2] * len(_threads())
