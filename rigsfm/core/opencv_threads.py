"""OpenCV on one thread for a block of work whose result must not depend on the threads' timing."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import cv2


@contextlib.contextmanager
def one_opencv_thread() -> Iterator[None]:
    """OpenCV on one thread inside the block, the caller's setting given back after it: several of its parallel
    routines combine their threads' parts in the order the threads finish, so their results vary between runs."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)
