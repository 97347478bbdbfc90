"""GPU SIFT where present: pycolmap's CUDA build (``pip install rigsfm[gpu]``, i.e. ``pycolmap-cuda12``) and a
CUDA device. The CPU stays the default everywhere else, and is what CI tests.

:func:`decide` is the whole decision (a pure function, tested without a GPU); :func:`use_gpu` feeds it
what this machine has: ``pycolmap.has_cuda`` (the build) and the number of CUDA devices the driver reports
(``cuDeviceGetCount`` from ``libcuda``, the driver's own library; 0 without a driver).
"""

from __future__ import annotations

import ctypes
import functools
import logging
from typing import TYPE_CHECKING

from rigsfm.core.errors import InputError
from rigsfm.run.options import Device

if TYPE_CHECKING:
    import pycolmap

logger = logging.getLogger(__name__)


def decide(requested: Device | str, *, has_cuda: bool, num_devices: int) -> bool:
    """Whether SIFT runs on the GPU: ``auto`` when pycolmap has CUDA and a device is there, ``cuda`` the same
    or a clear error, ``cpu`` never."""
    requested = Device(requested)
    if requested == Device.CPU:
        return False
    available = has_cuda and num_devices > 0
    if requested == Device.CUDA and not available:
        why = ("this pycolmap is built without CUDA: pip install 'rigsfm[gpu]' (pycolmap-cuda12) in place of pycolmap"
               if not has_cuda else "no CUDA device found (is the NVIDIA driver loaded?)")
        raise InputError(f"--device cuda: {why}; or use --device cpu")
    return available


@functools.cache
def cuda_device_count() -> int:
    """CUDA devices the driver reports; 0 when there is no driver or it fails."""
    for name in ("libcuda.so.1", "libcuda.so"):
        try:
            cuda = ctypes.CDLL(name)
        except OSError:
            continue
        count = ctypes.c_int(0)
        if cuda.cuInit(0) != 0 or cuda.cuDeviceGetCount(ctypes.byref(count)) != 0:
            return 0
        return int(count.value)
    return 0


def pycolmap_device(gpu: bool) -> pycolmap.Device:
    """The ``device`` argument of pycolmap's extraction and matching for this decision. It must always be given:
    pycolmap's default, ``Device.auto``, overrides ``use_gpu=False`` in the options and runs on the GPU whenever
    its build has CUDA, so ``--device cpu`` would silently extract on the GPU."""
    import pycolmap

    return pycolmap.Device.cuda if gpu else pycolmap.Device.cpu


@functools.cache
def use_gpu(requested: Device | str = Device.AUTO) -> bool:
    """:func:`decide` on this machine (the device count is only asked for when pycolmap has CUDA)."""
    import pycolmap

    has_cuda = bool(getattr(pycolmap, "has_cuda", False))
    gpu = decide(requested, has_cuda=has_cuda, num_devices=cuda_device_count() if has_cuda else 0)
    if gpu:
        logger.info("SIFT on the GPU (%d CUDA device(s))", cuda_device_count())
    return gpu
