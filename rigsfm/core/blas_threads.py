"""BLAS on one thread for a block of work that runs mostly on one core: OpenBLAS's idle threads wait for work by
spinning, and that CPU time is spent whether the block gains from them or not."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Every BLAS numpy and scipy have loaded on one thread inside the block, each one's own setting given back after
    it."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield
