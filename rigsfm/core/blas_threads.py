"""OpenBLAS on one thread for a block of work that runs mostly on one core: its idle threads wait for work by
spinning, and that CPU time is spent whether the block gains from them or not."""

from __future__ import annotations

import contextlib
import ctypes
import logging
from collections.abc import Iterator
from pathlib import Path

logger = logging.getLogger(__name__)

# numpy's and scipy's wheels each bundle their own OpenBLAS, under these names (the 64-bit integer build's suffix)
_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
            "openblas_set_num_threads")
_GETTERS = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
            "openblas_get_num_threads")


def _loaded_openblas() -> list[tuple[ctypes._FuncPointer, ctypes._FuncPointer]]:
    """(get, set) of every OpenBLAS this process has loaded (Linux's /proc/self/maps; none elsewhere)."""
    try:
        maps = Path("/proc/self/maps").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    paths = sorted({line.split()[-1] for line in maps.splitlines()
                    if "openblas" in line.rsplit("/", 1)[-1].lower() and line.split()[-1].startswith("/")})
    found = []
    for path in paths:
        try:
            library = ctypes.CDLL(path)  # already loaded: the same handle, no second copy
        except OSError:
            continue
        get = next((getattr(library, name) for name in _GETTERS if hasattr(library, name)), None)
        set_ = next((getattr(library, name) for name in _SETTERS if hasattr(library, name)), None)
        if get is not None and set_ is not None:
            get.restype, set_.argtypes = ctypes.c_int, [ctypes.c_int]
            found.append((get, set_))
    return found


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Every loaded OpenBLAS on one thread inside the block, each one's own setting given back after it."""
    libraries = _loaded_openblas()
    before = [get() for get, _ in libraries]
    for _, set_ in libraries:
        set_(1)
    try:
        yield
    finally:
        for (_, set_), threads in zip(libraries, before):
            set_(threads)
