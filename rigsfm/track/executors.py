"""Fan the independent per-frame registrations out with :mod:`rigsfm.core.executors` (a local process pool,
or a Ray cluster).

Each task calls :func:`rigsfm.track.register.register_frame` with picklable inputs and hands each record to
``on_result`` as soon as it is done (in completion order), so the caller can checkpoint. The reference map
is sent once per local worker, or put once into Ray's object store; for Ray, images are read here and sent
as bytes, so the workers need no shared file system (only rigsfm and pycolmap installed).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from rigsfm.core.errors import InputError
from rigsfm.core.executors import Executor, map_unordered
from rigsfm.track.options import RegistrationOptions
from rigsfm.track.reference import ReferenceMap
from rigsfm.track.register import FrameTask, register_frame

EXECUTORS = tuple(str(e) for e in Executor)
OnResult = Callable[[dict], None]


def _with_bytes(task: FrameTask) -> FrameTask:
    images: dict[str, Path | bytes] = {}
    for sensor, source in task.images.items():
        try:
            images[sensor] = Path(source).read_bytes() if isinstance(source, (str, Path)) else source
        except OSError as e:
            raise InputError(f"cannot read {source}: {e}") from e  # type: ignore[str-bytes-safe]  # only paths are read
    return replace(task, images=images)


def run_frames(tasks: Sequence[FrameTask], reference: ReferenceMap, on_result: OnResult, *,
               executor: str = "local", workers: int = 2, address: str | None = None,
               options: RegistrationOptions | None = None) -> None:
    """Register every task with the chosen executor; ``on_result`` gets each record when it is done."""
    options = options or RegistrationOptions()
    map_unordered(register_frame, tasks, on_result, executor=executor, workers=workers, address=address,
                  shared=(reference, options), prepare=_with_bytes)
