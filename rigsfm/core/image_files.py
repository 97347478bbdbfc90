"""Image files as stored: one reader for every part of rigsfm, and the EXIF Orientation check.

rigsfm works on the pixels as the file stores them, as COLMAP's feature extractor does: rigs.yaml's intrinsics,
every keypoint, scale.yaml's and matches.csv's pixel coordinates are in that frame. OpenCV's default read turns
the pixels as an EXIF Orientation tag says, so every OpenCV read here passes ``IMREAD_IGNORE_ORIENTATION``. An
image whose tag asks for a turn or a mirror (2-8) is refused where it enters (``run``, ``calibrate``, ``track``,
``pick``) rather than honoured: COLMAP never turns it, OpenCV's TIFF reader turns some orientations whatever the
flags and cannot read the others, and whether a calibration was made on the stored or on the turned pixels is
something only the user knows. :func:`refuse_turned_images` says which of the two fixes fits.
"""

from __future__ import annotations

import io
import shlex
import struct
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.names import quoted

ORIENTATION_TAG = 0x0112  # EXIF / TIFF IFD0
TURNS = {  # how a viewer shows an image of each Orientation value (1 = as stored)
    2: "mirrored left to right", 3: "turned 180°", 4: "mirrored top to bottom",
    5: "mirrored across its diagonal", 6: "turned 90° clockwise", 7: "mirrored across its anti-diagonal",
    8: "turned 90° counter-clockwise",
}
SWAPS_SIDES = {5, 6, 7, 8}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
MAX_IFD_ENTRIES = 4096  # more is not an EXIF block: give up rather than read a huge table


def read_image(path: Path | str, flags: int = cv2.IMREAD_COLOR) -> np.ndarray | None:
    """``cv2.imread`` of the pixels as stored (never turned by an EXIF tag), or None if the file cannot be read."""
    if not Path(path).is_file():
        return None  # said here, not by OpenCV's own warning on stderr
    return cv2.imread(str(path), flags | cv2.IMREAD_IGNORE_ORIENTATION)


def decode_image(data: bytes | bytearray | memoryview, flags: int = cv2.IMREAD_COLOR) -> np.ndarray | None:
    """``cv2.imdecode`` of an encoded file's bytes, the pixels as stored, or None if they do not decode."""
    return cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags | cv2.IMREAD_IGNORE_ORIENTATION)


def exif_orientation(source: Path | str | bytes | bytearray | memoryview) -> int | None:
    """The EXIF Orientation value (1-8) of a JPEG, PNG, TIFF or WebP file (a path or the file's bytes), None when
    it has none, an undefined value (which viewers ignore), or the file cannot be parsed (a damaged file is left to
    the decoder's own check). Reads the headers only, a few small reads per file."""
    try:
        if isinstance(source, (bytes, bytearray, memoryview)):
            value = _orientation(io.BytesIO(bytes(source)))
        else:
            with open(source, "rb") as f:
                value = _orientation(f)
    except (OSError, struct.error, ValueError):
        return None
    return value if value is not None and 1 <= value <= 8 else None


def is_turned(orientation: int | None) -> bool:
    """Whether viewers (and OpenCV's default read) show the image other than as stored."""
    return orientation in TURNS


def _orientation(f: BinaryIO) -> int | None:
    head = f.read(12)
    if head[:2] == b"\xff\xd8":
        return _jpeg(f)
    if head[:8] == PNG_SIGNATURE:
        return _png(f)
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return _tiff(f)
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return _webp(f)
    return None


def _tiff(f: BinaryIO, base: int = 0) -> int | None:
    """Orientation in IFD0 of a TIFF structure starting at ``base`` (a TIFF file, or an EXIF block's payload)."""
    f.seek(base)
    order = f.read(2)
    if order not in (b"II", b"MM"):
        return None
    endian = "<" if order == b"II" else ">"
    magic, ifd = struct.unpack(endian + "HI", f.read(6))
    if magic != 42:
        return None
    f.seek(base + ifd)
    (count,) = struct.unpack(endian + "H", f.read(2))
    if count > MAX_IFD_ENTRIES:
        return None
    table = f.read(12 * count)
    for k in range(len(table) // 12):
        tag, kind, _ = struct.unpack(endian + "HHI", table[12 * k:12 * k + 8])
        if tag == ORIENTATION_TAG:
            value = table[12 * k + 8:12 * k + 12]
            if kind == 3:  # SHORT, as the standard says
                return struct.unpack(endian + "H", value[:2])[0]
            if kind == 4:  # LONG, written by a few tools
                return struct.unpack(endian + "I", value)[0]
            return None
    return None


def _exif_block(data: bytes) -> int | None:
    if data[:6] == b"Exif\x00\x00":
        data = data[6:]
    return _tiff(io.BytesIO(data))


def _jpeg_segments(f: BinaryIO) -> Iterator[tuple[int, int]]:
    """(marker, data length) of each JPEG header segment before the image data, ``f`` at the segment's data."""
    f.seek(2)
    while True:
        byte = f.read(1)
        if byte != b"\xff":
            return
        marker = f.read(1)
        while marker == b"\xff":  # fill bytes
            marker = f.read(1)
        if not marker or marker in (b"\xd9", b"\xda"):  # end of image, start of scan: no more headers
            return
        if 0xD0 <= marker[0] <= 0xD7 or marker == b"\x01":  # markers without a length
            continue
        (length,) = struct.unpack(">H", f.read(2))
        if length < 2:
            return
        start = f.tell()
        yield marker[0], length - 2
        f.seek(start + length - 2)


def _jpeg(f: BinaryIO) -> int | None:
    """The first APP1 Exif segment before the image data, as OpenCV and viewers read it."""
    for marker, length in _jpeg_segments(f):
        if marker == 0xE1:
            data = f.read(length)
            if data[:6] == b"Exif\x00\x00":
                return _exif_block(data)
    return None


JPEG_FRAME_MARKERS = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # SOF0-15: not DHT, JPG, DAC


def stored_size(path: Path | str) -> tuple[int, int] | None:
    """(width, height) of a PNG or JPEG file from its header, no pixels decoded; None for other formats or a
    header that does not say (then the pixels tell)."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            if head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                return width, height
            if head[:2] == b"\xff\xd8":
                for marker, _ in _jpeg_segments(f):
                    if marker in JPEG_FRAME_MARKERS:
                        _, height, width = struct.unpack(">BHH", f.read(5))
                        return width, height
    except (OSError, struct.error):
        return None
    return None


def _png(f: BinaryIO) -> int | None:
    """The eXIf chunk, wherever it is (viewers read one after the image data too)."""
    return _chunked(f, start=8, header=">I4s", exif=b"eXIf", end=b"IEND", after=lambda length: 4)  # the CRC


def _webp(f: BinaryIO) -> int | None:
    return _chunked(f, start=12, header="<4sI", exif=b"EXIF", end=None,
                    after=lambda length: length & 1)  # RIFF pads each chunk to an even size


def _chunked(f: BinaryIO, *, start: int, header: str, exif: bytes, end: bytes | None,
             after: Callable[[int], int]) -> int | None:
    """Orientation in the first ``exif`` chunk of a file of chunks from byte ``start`` on (PNG, RIFF), reading
    the headers only: each chunk is an 8-byte ``header`` (its data's length and its kind, in either order), the
    data, then ``after(length)`` bytes; no chunk after one of kind ``end`` counts."""
    f.seek(start)
    while True:
        head = f.read(8)
        if len(head) < 8:
            return None
        first, second = struct.unpack(header, head)
        length, kind = (first, second) if isinstance(first, int) else (second, first)
        if kind == exif:
            return _exif_block(f.read(length))
        if kind == end:
            return None
        f.seek(length + after(length), io.SEEK_CUR)


def refuse_turned_images(paths: Sequence[Path], *, folder: Path | None = None,
                         calibration: Callable[[Path], tuple[str, int, int] | None] | None = None,
                         then: str = "") -> None:
    """Raise one InputError naming the files among ``paths`` whose EXIF Orientation asks viewers to turn or
    mirror them, with the fix: remove the tag when the calibration was made on the pixels as stored, turn the
    pixels when it was made on the images as shown. ``calibration(path)`` gives (which camera, width, height)
    to tell the two apart by size; ``folder`` is what the commands should work on (exiftool recursively,
    the others by a glob); ``then`` is added to the advice (e.g. to treat other images the same way)."""
    turned: list[tuple[Path, int]] = [(Path(p), o) for p in paths  # type: ignore[misc]  # is_turned: not None
                                      if is_turned(o := exif_orientation(p))]
    if not turned:
        return
    first, orientation = turned[0]
    names = f"'{first}'" if len(turned) == 1 else (
        f"'{first}' and {len(turned) - 1} more ({quoted(p for p, _ in turned[1:3])}"
        f"{', ...' if len(turned) > 3 else ''})")
    strip = f"`exiftool -Orientation=1 -n -overwrite_original {_targets(turned, folder, recursive=True)}`"
    each = _targets(turned, folder, recursive=False)
    turn = f"`mogrify -auto-orient {each}`, or `exiftran -ai {each}` for JPEG without loss"
    stored = read_image(first, cv2.IMREAD_UNCHANGED)
    camera = calibration(first) if calibration is not None else None
    if stored is not None and camera is not None:
        label, width, height = camera
        stored_size = (stored.shape[1], stored.shape[0])
        shown_size = stored_size[::-1] if orientation in SWAPS_SIDES else stored_size
        if stored_size == (width, height) and shown_size != (width, height):
            advice = (f"the stored {width}x{height} pixels are what {label} is calibrated for: remove the tag and "
                      f"keep the pixels ({strip})")
        elif shown_size == (width, height) and stored_size != (width, height):
            advice = (f"{label} is calibrated for the image as shown ({width}x{height}), not as stored "
                      f"({stored_size[0]}x{stored_size[1]}): turn the pixels as the tag says ({turn})")
        else:
            advice = (f"remove the tag ({strip}) if {label} was calibrated on the pixels as stored, or turn the "
                      f"pixels as the tag says ({turn}) if it was calibrated on the images as shown")
    else:
        advice = f"remove the tag ({strip}) or turn the pixels as the tag says ({turn})"
    raise InputError(
        f"{names} {'carries' if len(turned) == 1 else 'carry'} the EXIF tag Orientation={orientation} (viewers "
        f"show {'it' if len(turned) == 1 else 'them'} {TURNS[orientation]}), but rigsfm, like COLMAP, works on the "
        f"pixels as stored; {advice}{then}"
    )


def _targets(turned: list[tuple[Path, int]], folder: Path | None, *, recursive: bool) -> str:
    """What a shell command should work on: the one file, the folder (``-r``), a glob of the files' depth and
    suffix under ``folder``, or FILE; quoted for the shell where a name needs it."""
    if len(turned) == 1:
        return shlex.quote(str(turned[0][0]))
    if folder is not None and recursive:
        return f"-r {shlex.quote(str(folder))}"
    if folder is not None:
        shapes = {(len(p.relative_to(folder).parts), p.suffix) for p, _ in turned if p.is_relative_to(folder)}
        if len(shapes) == 1 and all(p.is_relative_to(folder) for p, _ in turned):
            depth, suffix = shapes.pop()
            return f"{shlex.quote(str(folder))}/{'*/' * (depth - 1)}*{suffix}"
    return "FILE"
