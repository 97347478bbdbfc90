"""COLMAP's binary model files walked record by record before pycolmap reads them.

pycolmap trusts every count in ``cameras.bin``, ``images.bin``, ``points3D.bin``, ``rigs.bin`` and ``frames.bin``:
reading past the end of a cut file yields garbage counts, which it reserves and loops over (gigabytes and
minutes for a cut file). Here each file's records are checked to fit its size, counts against the
bytes left, camera models against COLMAP's list and the ids each file refers to against the others, so that a
truncated or damaged model is named at once and pycolmap only ever sees a consistent one.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# COLMAP's camera model ids and their parameter counts (src/colmap/sensor/models.h); pycolmap 4.2 lists the same.
CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4, 13: 5, 14: 3,
                 15: 4, 16: 6, 17: 2}
SENSOR_TYPES = (0, 1)  # CAMERA, IMU
INVALID_POINT3D = 2**64 - 1
MAX_NAME = 4096  # bytes of an image name; a longer one is a missing terminator


class ModelFileError(ValueError):
    """What is wrong with one file of a model (``path``): ``what`` says where it goes wrong."""

    def __init__(self, path: Path, what: str):
        super().__init__(f"{path}: {what}")
        self.path, self.what = path, what


class _Cursor:
    """Reads little-endian fields from one file's bytes, refusing any read past its end."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.offset = 0

    def fail(self, what: str) -> ModelFileError:
        return ModelFileError(self.path, f"{len(self.data)} B; {what}")

    def read(self, fmt: struct.Struct, what: str) -> tuple:
        end = self.offset + fmt.size
        if end > len(self.data):
            raise self.fail(f"cut short in {what}")
        values = fmt.unpack_from(self.data, self.offset)
        self.offset = end
        return values

    def skip(self, size: int, what: str) -> None:
        if size > len(self.data) - self.offset:
            raise self.fail(f"cut short in {what} ({size} B more needed)")
        self.offset += size

    def count(self, fmt: struct.Struct, record_size: int, what: str) -> int:
        """A count of records of at least ``record_size`` bytes each, checked against the bytes left."""
        (n,) = self.read(fmt, f"the number of {what}")
        if n * record_size > len(self.data) - self.offset:
            raise self.fail(f"says {n} {what} but only {len(self.data) - self.offset} B follow")
        return n

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset, self.offset + MAX_NAME)
        if end < 0:
            raise self.fail(f"{what}: no end of the name within {MAX_NAME} B")
        raw = self.data[self.offset:end]
        self.offset = end + 1
        return raw.decode("utf-8", errors="replace")

    def finish(self) -> None:
        if self.offset != len(self.data):
            raise self.fail(f"{len(self.data) - self.offset} B after its last record")


U64 = struct.Struct("<Q")
U32 = struct.Struct("<I")
CAMERA = struct.Struct("<IiQQ")
SENSOR = struct.Struct("<iI")
POSE = struct.Struct("<7d")
RIG_SENSOR = struct.Struct("<iIB")
FRAME = struct.Struct("<II7dI")
DATA_ID = struct.Struct("<iIQ")
IMAGE = struct.Struct("<I7dI")
POINT2D = 24  # x, y (double) and point3D_id (uint64)
POINT3D = struct.Struct("<Q3d3BdQ")
TRACK_ELEMENT = 8  # image_id, point2D_idx (uint32 each)


@dataclass
class ModelIds:
    """The ids each file defines, for the references between files."""

    cameras: set[int] = field(default_factory=set)
    rigs: set[int] = field(default_factory=set)
    frame_images: set[int] = field(default_factory=set)
    images: dict[int, int] = field(default_factory=dict)  # image_id -> number of 2D points


def _cameras(path: Path, ids: ModelIds) -> None:
    cursor = _Cursor(path)
    for i in range(cursor.count(U64, CAMERA.size, "cameras")):
        camera_id, model, width, height = cursor.read(CAMERA, f"camera {i + 1}")
        if model not in CAMERA_PARAMS:
            raise cursor.fail(f"camera {camera_id} has camera model id {model}, which COLMAP does not know")
        cursor.skip(8 * CAMERA_PARAMS[model], f"camera {camera_id}'s parameters")
        ids.cameras.add(camera_id)
    cursor.finish()


def _rigs(path: Path, ids: ModelIds) -> None:
    cursor = _Cursor(path)
    for i in range(cursor.count(U64, U32.size * 2, "rigs")):
        rig_id, sensors = cursor.read(struct.Struct("<II"), f"rig {i + 1}")
        # the reference sensor (type, id) then each other one with its pose flag: the least those can take
        if sensors and SENSOR.size + (sensors - 1) * RIG_SENSOR.size > len(cursor.data) - cursor.offset:
            raise cursor.fail(f"rig {rig_id} says {sensors} sensors but the file is shorter")
        for k in range(sensors):
            if k == 0:
                (kind, _) = cursor.read(SENSOR, f"rig {rig_id}'s reference sensor")
            else:
                kind, _, has_pose = cursor.read(RIG_SENSOR, f"rig {rig_id}'s sensor {k + 1}")
                if has_pose not in (0, 1):
                    raise cursor.fail(f"rig {rig_id}'s sensor {k + 1}: pose flag {has_pose}")
                if has_pose:
                    cursor.skip(POSE.size, f"rig {rig_id}'s sensor {k + 1} pose")
            if kind not in SENSOR_TYPES:
                raise cursor.fail(f"rig {rig_id}: sensor type {kind}")
        ids.rigs.add(rig_id)
    cursor.finish()


def _frames(path: Path, ids: ModelIds) -> None:
    cursor = _Cursor(path)
    for i in range(cursor.count(U64, FRAME.size, "frames")):
        frame_id, rig_id, *_, data_ids = cursor.read(FRAME, f"frame {i + 1}")
        if rig_id not in ids.rigs:
            raise cursor.fail(f"frame {frame_id} refers to rig {rig_id}, which rigs.bin does not hold")
        if data_ids * DATA_ID.size > len(cursor.data) - cursor.offset:
            raise cursor.fail(f"frame {frame_id} says {data_ids} images but the file is shorter")
        for _ in range(data_ids):
            kind, _, data_id = cursor.read(DATA_ID, f"frame {frame_id}'s data")
            if kind not in SENSOR_TYPES:
                raise cursor.fail(f"frame {frame_id}: sensor type {kind}")
            if kind == 0:
                ids.frame_images.add(data_id)
    cursor.finish()


def _images(path: Path, ids: ModelIds, with_frames: bool) -> None:
    cursor = _Cursor(path)
    for i in range(cursor.count(U64, IMAGE.size + 1 + U64.size, "images")):
        image_id, *_, camera_id = cursor.read(IMAGE, f"image {i + 1}")
        if camera_id not in ids.cameras:
            raise cursor.fail(f"image {image_id} refers to camera {camera_id}, which cameras.bin does not hold")
        if with_frames and image_id not in ids.frame_images:
            raise cursor.fail(f"image {image_id} is in no frame of frames.bin")
        cursor.name(f"image {image_id}")
        (points,) = cursor.read(U64, f"image {image_id}'s number of 2D points")
        cursor.skip(points * POINT2D, f"image {image_id}'s {points} 2D points")
        ids.images[image_id] = points
    cursor.finish()


def _points3d(path: Path, ids: ModelIds) -> None:
    cursor = _Cursor(path)
    data, size, end = cursor.data, POINT3D.size, len(cursor.data)
    track_at = size - U64.size  # the track length ends the fixed part of a point
    track_length = U64.unpack_from
    starts, lengths = [], []
    offset = None
    for i in range(cursor.count(U64, size, "3D points")):  # the one loop per point: kept to the bare reads
        offset = cursor.offset
        if offset + size > end:
            raise cursor.fail(f"cut short in 3D point {i + 1}")
        (track,) = track_length(data, offset + track_at)
        offset += size
        starts.append(offset)
        lengths.append(track)
        cursor.offset = offset + TRACK_ELEMENT * track
        if cursor.offset > end:
            raise cursor.fail(f"cut short in 3D point {i + 1}'s track of {track}")
    cursor.finish()
    _check_tracks(cursor, np.asarray(starts, np.int64), np.asarray(lengths, np.int64), ids.images)


def _check_tracks(cursor: _Cursor, starts: np.ndarray, lengths: np.ndarray, images: dict[int, int]) -> None:
    """Every track element names an image of images.bin and one of its 2D points (pycolmap indexes with it)."""
    data = cursor.data
    words = [np.frombuffer(data, "<u4", count=(len(data) - r) // 4, offset=r) for r in range(4)]  # by alignment
    known = np.array(sorted(images), np.int64)
    counts = np.array([images[k] for k in sorted(images)], np.int64)
    chunk = 1 << 16  # points at a time: bounded memory
    for first in range(0, len(starts), chunk):
        s, n = starts[first:first + chunk], lengths[first:first + chunk]
        total = int(n.sum())
        if not total:
            continue
        point = np.repeat(np.arange(len(s)), n)
        offsets = s[point] + (np.arange(total) - np.repeat(np.cumsum(n) - n, n)) * TRACK_ELEMENT
        image_ids, point2d = np.empty(total, np.int64), np.empty(total, np.int64)
        for r in range(4):
            mask = (offsets & 3) == r
            index = (offsets[mask] - r) >> 2
            image_ids[mask], point2d[mask] = words[r][index], words[r][index + 1]
        slot = np.clip(np.searchsorted(known, image_ids), 0, max(len(known) - 1, 0))
        ok = ((known[slot] == image_ids) & (point2d < counts[slot])) if len(known) else np.zeros(total, bool)
        if not ok.all():
            bad = int(np.argmin(ok))
            raise cursor.fail(f"3D point {first + int(point[bad]) + 1} is seen by 2D point {point2d[bad]} of image "
                              f"{image_ids[bad]}, which images.bin does not hold")


def check_model_files(folder: Path) -> None:
    """Walk the binary model in ``folder`` (rigs and frames where present); a ``ModelFileError`` naming the first
    file that is cut short, damaged or refers to what another file lacks."""
    folder = Path(folder)
    ids = ModelIds()
    with_frames = (folder / "rigs.bin").is_file() or (folder / "frames.bin").is_file()
    if with_frames:
        for name in ("rigs.bin", "frames.bin"):
            if not (folder / name).is_file():
                other = "frames.bin" if name == "rigs.bin" else "rigs.bin"
                raise ModelFileError(folder / name, f"missing, while {other} is there")
        _rigs(folder / "rigs.bin", ids)
    _cameras(folder / "cameras.bin", ids)
    if with_frames:
        _frames(folder / "frames.bin", ids)
    _images(folder / "images.bin", ids, with_frames)
    _points3d(folder / "points3D.bin", ids)
