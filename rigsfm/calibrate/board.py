"""Calibration boards: the ``board.yaml`` spec, corner detection, and diagnosis of a wrong spec.

Corner identifiers are the link between views: for a chessboard the id of inner corner (col, row) is
``row * cols + col`` (OpenCV's ``findChessboardCorners`` order); for ChArUco it is OpenCV's ChArUco corner
id. ``BoardSpec.object_points()[ids]`` gives the board coordinates (metres, z = 0) of detected corners,
so partial views (ChArUco seen by a narrow camera) need no special handling downstream.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image
from rigsfm.core.io import load_yaml_or_json

logger = logging.getLogger(__name__)

BOARD_TYPES = ("chessboard", "charuco")
ARUCO_DICTIONARIES = tuple(
    name for name in dir(cv2.aruco) if name.startswith("DICT_") and name == name.upper()
)
MIN_CORNERS = 6  # fewer corners than this in one view are not used for calibration
DETECTION_MAX_SIDE = 2000  # chessboards are searched on a downscaled copy of larger images


@dataclass(frozen=True)
class BoardSpec:
    """A planar calibration board; lengths in metres. ``cols x rows`` is ``inner_corners`` or ``squares``."""

    type: str
    square: float
    inner_corners: tuple[int, int] | None = None  # chessboard: inner corners (cols, rows)
    squares: tuple[int, int] | None = None  # charuco: squares (cols, rows)
    marker: float | None = None  # charuco: marker side
    dictionary: str | None = None  # charuco: e.g. DICT_5X5_100
    legacy_pattern: bool = False  # charuco boards printed with OpenCV < 4.6 and an even row count

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(cols, rows) of the inner-corner grid."""
        if self.type == "chessboard":
            return self.inner_corners  # type: ignore[return-value]
        return (self.squares[0] - 1, self.squares[1] - 1)  # type: ignore[index]

    def object_points(self) -> np.ndarray:
        """(N, 3) board coordinates of every corner, indexed by corner id."""
        if self.type == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        cols, rows = self.corner_grid
        grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64) * self.square
        return np.hstack([grid, np.zeros((len(grid), 1))])

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        # the board type's fields are set (parse_board)
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))  # type: ignore[arg-type]
        board = cv2.aruco.CharucoBoard(tuple(self.squares), self.square, self.marker, dictionary)  # type: ignore[arg-type]
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def describe(self) -> str:
        if self.type == "chessboard":
            # the board type's fields are set (parse_board)
            return f"chessboard, {self.inner_corners[0]}x{self.inner_corners[1]} inner corners, {self.square} m squares"  # type: ignore[index]
        return (f"ChArUco {self.squares[0]}x{self.squares[1]} squares, {self.square} m squares, "  # type: ignore[index]
                f"{self.marker} m markers, {self.dictionary}" + (", legacy pattern" if self.legacy_pattern else ""))


def _pair(value, key: str, where: str, minimum: int) -> tuple[int, int]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise InputError(f"{where}: '{key}' must be a list of two integers [cols, rows], got {value!r}")
    try:
        pair = (int(value[0]), int(value[1]))
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: '{key}' must be two integers, got {value!r}") from e
    if min(pair) < minimum or pair[0] != value[0] or pair[1] != value[1]:
        raise InputError(f"{where}: '{key}' must be integers >= {minimum}, got {value!r}")
    return pair


def _length(data: dict, key: str, where: str) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise InputError(f"{where}: '{key}' must be a positive length in metres, got {value!r}")
    if value > 1.0:
        raise InputError(f"{where}: '{key}' = {value} looks like millimetres; board lengths are in metres")
    return float(value)


def board_spec_from_dict(data: dict, where: str = "board spec") -> BoardSpec:
    """Validate a board description (the content of ``board.yaml``)."""
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a mapping with 'type' and the board dimensions")
    kind = str(data.get("type", "")).lower()
    if kind not in BOARD_TYPES:
        raise InputError(f"{where}: 'type' must be one of {', '.join(BOARD_TYPES)}, got {data.get('type')!r}")
    square = _length(data, "square", where)
    if kind == "chessboard":
        if "inner_corners" not in data:
            raise InputError(f"{where}: a chessboard needs 'inner_corners: [cols, rows]' (squares minus one)")
        corners = _pair(data["inner_corners"], "inner_corners", where, 3)  # OpenCV finds 3x3 or more (else raises)
        return BoardSpec(type=kind, square=square, inner_corners=corners)
    for key in ("squares", "marker", "dictionary"):
        if key not in data:
            raise InputError(f"{where}: a charuco board needs 'squares', 'square', 'marker' and 'dictionary'")
    squares = _pair(data["squares"], "squares", where, 2)
    marker = _length(data, "marker", where)
    if marker >= square:
        raise InputError(f"{where}: 'marker' ({marker} m) must be smaller than 'square' ({square} m)")
    dictionary = str(data["dictionary"]).upper()
    if not dictionary.startswith("DICT_"):
        dictionary = "DICT_" + dictionary
    if dictionary not in ARUCO_DICTIONARIES:
        raise InputError(f"{where}: unknown ArUco dictionary {data['dictionary']!r}; use e.g. DICT_5X5_100")
    spec = BoardSpec(type=kind, square=square, squares=squares, marker=marker, dictionary=dictionary,
                     legacy_pattern=bool(data.get("legacy_pattern", False)))
    n_markers = squares[0] * squares[1] // 2
    available = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    if n_markers > available:
        raise InputError(f"{where}: a {squares[0]}x{squares[1]} ChArUco board needs {n_markers} markers but "
                         f"{dictionary} has only {available}; check 'squares' and 'dictionary'")
    return spec


def load_board_spec(path: Path) -> BoardSpec:
    return board_spec_from_dict(load_yaml_or_json(Path(path), "board", form="it gives 'type:' and the board's size "
                                                   "(docs/inputs.md, Calibrating the rigs)"), str(path))


@dataclass
class Detection:
    """Corners of the board found in one image: ids and OpenCV pixel coordinates (N, 2)."""

    ids: np.ndarray
    image_points: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def read_gray(path: Path) -> np.ndarray:
    image = read_image(path, cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"cannot read image {path}; is it a valid image file?")
    return image


def _subpix_window(corners: np.ndarray, grid: tuple[int, int]) -> int:
    pts = corners.reshape(grid[1], grid[0], 2)
    spacing = min(np.linalg.norm(np.diff(pts, axis=1), axis=2).min(), np.linalg.norm(np.diff(pts, axis=0), axis=2).min())
    return int(np.clip(round(0.4 * spacing), 3, 11))


def find_chessboard(gray: np.ndarray, grid: tuple[int, int], fast: bool = False) -> np.ndarray | None:
    """Inner corners (N, 2) of a ``grid = (cols, rows)`` chessboard, sub-pixel refined, or None."""
    scale = min(1.0, DETECTION_MAX_SIDE / max(gray.shape))
    small = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | (cv2.CALIB_CB_FAST_CHECK if fast else 0)
    found, corners = cv2.findChessboardCorners(small, grid, flags=flags)
    if not found:
        return None
    corners = corners.reshape(-1, 2).astype(np.float64)
    if scale != 1.0:
        corners = (corners + 0.5) / scale - 0.5
    win = _subpix_window(corners, grid)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    refined = cv2.cornerSubPix(gray, corners.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64)


class BoardDetector:
    """Detects one board spec in grayscale images."""

    def __init__(self, spec: BoardSpec):
        self.spec = spec
        if spec.type == "charuco":
            self.board = spec.charuco_board()
            self.detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, gray: np.ndarray) -> Detection | None:
        if self.spec.type == "chessboard":
            corners = find_chessboard(gray, self.spec.corner_grid)
            if corners is None:
                return None
            return Detection(ids=np.arange(len(corners)), image_points=corners)
        corners, ids, _, _ = self.detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        ids = ids.reshape(-1).astype(np.int64)
        if self.board.checkCharucoCornersCollinear(ids.reshape(-1, 1).astype(np.int32)):
            return None
        order = np.argsort(ids)
        return Detection(ids=ids[order], image_points=corners.reshape(-1, 2).astype(np.float64)[order])

    def detect_markers(self, gray: np.ndarray) -> np.ndarray:
        """ArUco marker ids seen in the image (charuco only); used to diagnose a wrong spec."""
        _, _, _, marker_ids = self.detector.detectBoard(gray)
        return np.zeros(0, np.int64) if marker_ids is None else marker_ids.reshape(-1)


def _probe_images(paths: list[Path], count: int = 4) -> list[np.ndarray]:
    step = max(1, len(paths) // count)
    return [read_gray(p) for p in paths[::step][:count]]


def _downscaled(gray: np.ndarray) -> np.ndarray:
    scale = min(1.0, DETECTION_MAX_SIDE / max(gray.shape))
    return gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _oriented(grid: tuple[int, int], like: tuple[int, int]) -> tuple[int, int]:
    """``grid`` with its longer side where ``like`` has it (a board counted [6, 9] or [9, 6] is the same board)."""
    return grid if (grid[0] >= grid[1]) == (like[0] >= like[1]) else (grid[1], grid[0])


def chessboard_size(images: list[np.ndarray], like: tuple[int, int], limit: int = 40) -> tuple[int, int] | None:
    """The inner corners (cols, rows) of the chessboard that ``images`` show, oriented as ``like``, or None.

    OpenCV's sector-based detector, allowed a larger board than a 3x3 part (CALIB_CB_LARGER), proposes each image's
    whole board; it errs at times (a row too many), so the largest proposal that the detector calibrate uses also
    finds wins, and grows while a grid one corner larger is found there too. Where nothing is proposed, grids one
    corner about ``like`` are tried, as the count of squares or of one side is the usual slip."""
    def found(grid: tuple[int, int], image: np.ndarray) -> bool:
        return min(grid) >= 3 and find_chessboard(image, grid, fast=True) is not None  # OpenCV needs 3 or more

    proposed: dict[tuple[int, int], list[np.ndarray]] = {}
    for image in images:
        ok, _, meta = cv2.findChessboardCornersSBWithMeta(_downscaled(image), (3, 3),
                                                           cv2.CALIB_CB_LARGER | cv2.CALIB_CB_EXHAUSTIVE)
        if ok and meta is not None and min(meta.shape[:2]) >= 3:
            proposed.setdefault(_oriented((meta.shape[1], meta.shape[0]), like), []).append(image)
    cols, rows = like
    near = [(cols - 1, rows - 1), (cols + 1, rows + 1), (cols - 1, rows), (cols, rows - 1), (cols + 1, rows),
            (cols, rows + 1), (cols - 2, rows - 2)]
    tries = [(grid, proposed[grid]) for grid in sorted(proposed, key=lambda g: -g[0] * g[1])]
    tries += [(grid, images) for grid in near if grid not in proposed]
    for grid, where in tries:
        for board in (grid, grid[::-1]):
            hits = [image for image in where if found(board, image)]
            if hits:
                break
        else:
            continue
        while max(board) < limit:
            larger = [g for g in ((board[0] + 1, board[1]), (board[0], board[1] + 1)) if found(g, hits[0])]
            if not larger:
                break
            board = larger[0]
        return _oriented(board, like)
    return None


def _square_means(gray: np.ndarray, homography: np.ndarray, centres: np.ndarray, radius: float = 0.15
                  ) -> np.ndarray | None:
    """Mean intensity of a patch (``radius`` squares) about each of ``centres`` (board squares, mapped into the
    image by ``homography``), or None where a patch leaves the image."""
    steps = np.linspace(-radius, radius, 5)
    offsets = np.array([(dx, dy) for dx in steps for dy in steps])
    points = (centres[:, None, :] + offsets[None]).reshape(-1, 1, 2)
    pixels = cv2.perspectiveTransform(points.astype(np.float64), homography).reshape(len(centres), -1, 2)
    x, y = np.round(pixels[..., 0]), np.round(pixels[..., 1])
    if not (np.isfinite(pixels).all() and (x >= 0).all() and (y >= 0).all() and (x < gray.shape[1]).all()
            and (y < gray.shape[0]).all()):
        return None
    return gray[y.astype(int), x.astype(int)].astype(np.float64).mean(axis=1)


def chessboard_beyond(gray: np.ndarray, corners: np.ndarray, grid: tuple[int, int], limit: int = 40
                      ) -> tuple[int, int, int, int]:
    """Inner corners the chessboard has beyond the found ``grid`` (cols, rows) of ``corners`` on each side (before
    the first column, after the last, before the first row, after the last): walking outwards one line of corners at
    a time, a line exists where the squares on both sides of it continue the checkerboard (each square's colour the
    parity predicts, at a fair part of the found grid's contrast). A whole board's outer squares are followed by its
    margin, which does not alternate. Each step extrapolates one square from the last three lines (a homography:
    lens distortion bends the board over longer reaches) and refines the new line's corners."""
    cols, rows = grid
    points = corners.reshape(rows, cols, 2)
    board = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64)
    homography, _ = cv2.findHomography(board, corners)
    inside = np.array([(c + 0.5, r + 0.5) for r in range(rows - 1) for c in range(cols - 1)])
    parity = (np.floor(inside).sum(axis=1) % 2).astype(int)
    means = _square_means(gray, homography, inside)
    if means is None:
        return (0, 0, 0, 0)
    dark_parity = int(means[parity == 1].mean() < means[parity == 0].mean())
    contrast = abs(means[parity == 0].mean() - means[parity == 1].mean())
    window = _subpix_window(corners, grid)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)

    def at(axis: int, position: float, along: np.ndarray) -> np.ndarray:  # board coordinates of a line's points
        fixed = np.full(len(along), position)
        return np.c_[fixed, along] if axis == 0 else np.c_[along, fixed]

    def alternates(homography: np.ndarray, axis: int, position: float, along: np.ndarray) -> bool:
        centres = at(axis, position, along[:-1] + 0.5)
        means = _square_means(gray, homography, centres)
        if means is None:
            return False
        dark = (np.floor(centres).sum(axis=1) % 2).astype(int) == dark_parity
        step = means[~dark].mean() - means[dark].mean()
        # the outer squares of a printed board are often cut narrower: a part of the contrast is enough
        return bool(step >= BEYOND_CONTRAST * contrast and
                    np.all((means > 0.5 * (means[~dark].mean() + means[dark].mean())) == ~dark))

    found = []
    for axis, sign in ((0, -1), (0, 1), (1, -1), (1, 1)):
        count = rows if axis == 0 else cols
        along = np.arange(count, dtype=np.float64)
        order = range(cols if axis == 0 else rows)
        lines = [(float(k), points[:, k] if axis == 0 else points[k, :]) for k in (order if sign > 0 else order[::-1])]
        extra = 0
        while extra < limit:
            last = lines[-3:]
            local, _ = cv2.findHomography(np.concatenate([at(axis, k, along) for k, _ in last]),
                                          np.concatenate([p for _, p in last]))
            edge = last[-1][0]
            if local is None or not all(alternates(local, axis, edge + sign * d, along) for d in (0.5, 1.5)):
                break
            guess = cv2.perspectiveTransform(at(axis, edge + sign, along).reshape(-1, 1, 2), local).astype(np.float32)
            line = cv2.cornerSubPix(gray, guess, (window, window), (-1, -1), criteria).reshape(-1, 2)
            lines.append((edge + sign, line.astype(np.float64)))
            extra += 1
        found.append(extra)
    return found[0], found[1], found[2], found[3]


BEYOND_CONTRAST = 0.3  # of the found grid's dark-light contrast, a square beyond it must show (chessboard_beyond)


def _larger_part(gray: np.ndarray, grid: tuple[int, int]) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """Where ``gray`` shows a chessboard larger than ``grid`` about the part found: a grid one corner larger that
    OpenCV finds, and the board's count that the walk outwards gives (chessboard_beyond); None where it shows none."""
    cols, rows = grid
    larger = next((g for g in ((cols + 1, rows), (cols, rows + 1)) if find_chessboard(gray, g, fast=True) is not None),
                  None)
    corners = find_chessboard(gray, grid)
    beyond = (0, 0, 0, 0) if corners is None else chessboard_beyond(gray, corners, grid)
    if larger is None and not any(beyond):
        return None
    walked = _oriented((cols + beyond[0] + beyond[1], rows + beyond[2] + beyond[3]), grid)
    return larger or ((cols + 1, rows) if beyond[0] or beyond[1] else (cols, rows + 1)), walked


def _whole_board(gray: np.ndarray, grid: tuple[int, int], larger: tuple[int, int], walked: tuple[int, int]
                 ) -> tuple[int, int] | None:
    """The count of the board ``gray`` shows, at least ``larger``: OpenCV's proposal (chessboard_size), or the
    walk's where OpenCV finds that whole grid; None where neither is found."""
    whole = chessboard_size([gray], grid)
    if whole is None or whole[0] * whole[1] < walked[0] * walked[1]:
        if any(find_chessboard(gray, g) is not None for g in (walked, walked[::-1])):
            whole = walked
    return whole if whole is not None and whole[0] * whole[1] >= larger[0] * larger[1] else None


def refuse_part_of_a_larger_chessboard(spec: BoardSpec, detected: list[Path], where: str, probes: int = 2,
                                       namers: int = 4) -> None:
    """Raise where the images show a chessboard with more inner corners than ``spec``: OpenCV then finds a part of
    it, and which part can differ between images and between a rig's two cameras (E^sl off by whole squares).
    ``detected``: images in which ``spec`` was found; a few of them (``probes``), spread out, are searched one corner
    larger and walked outwards from the part found (chessboard_beyond: OpenCV rarely finds a grid one corner larger
    than a small part, e.g. 5x3 about a 4x3 part of a 9x6 board). Where one shows a larger board, its count is named
    from the first of up to ``namers`` images whose whole board OpenCV finds (a small part can lie on a board
    that leaves the image, or on a screen showing one)."""
    grid: tuple[int, int] = spec.inner_corners  # type: ignore[assignment]  # set for a chessboard (parse_board)
    spread = detected[::max(1, len(detected) // probes)]
    found = next(((path, part) for path in spread[:probes] if (part := _larger_part(read_gray(path), grid))), None)
    if found is None:
        return
    path, (larger, walked) = found
    named = None
    for other in [path] + [p for p in detected[::max(1, len(detected) // namers)] if p != path][:namers - 1]:
        gray = read_gray(other)
        part = (larger, walked) if other == path else _larger_part(gray, grid)
        if part is not None and (named := _whole_board(gray, grid, larger, part[1])) is not None:
            path = other
            break
    count = (f"inner_corners [{named[0]}, {named[1]}]" if named is not None
             else f"at least inner_corners [{larger[0]}, {larger[1]}]")
    raise InputError(f"{where}: {path.name} shows a chessboard with {count}, more than board.yaml's "
                     f"[{grid[0]}, {grid[1]}]: only a part of the board would be used, and which part can differ "
                     "between images and cameras; fix 'inner_corners' in board.yaml (count inner corners = squares "
                     "- 1)")


def diagnose_no_detection(spec: BoardSpec, paths: list[Path], where: str) -> InputError:
    """An error explaining why ``spec`` was found in none of ``paths``, with a corrected spec if one fits."""
    images = _probe_images(paths)
    base = f"{where}: the board ({spec.describe()}) was found in none of the {len(paths)} images"
    if spec.type == "chessboard":
        grid = chessboard_size(images, spec.inner_corners)  # type: ignore[arg-type]  # set for a chessboard
        if grid is not None:
            return InputError(f"{base}, but a chessboard with inner_corners [{grid[0]}, {grid[1]}] was found: "
                              "fix 'inner_corners' in board.yaml (count inner corners = squares - 1)")
        return InputError(f"{base}, nor a chessboard of another size; check 'inner_corners' ([cols, rows], squares "
                          "- 1) and that the whole board is visible, sharp and well lit")
    detector = BoardDetector(spec)
    markers = np.concatenate([detector.detect_markers(im) for im in images])
    if len(markers) == 0:
        for name in ARUCO_DICTIONARIES:
            if name == spec.dictionary:
                continue
            other = BoardSpec(type="charuco", square=spec.square, squares=spec.squares, marker=spec.marker,
                              dictionary=name)
            try:
                if any(len(BoardDetector(other).detect_markers(im)) >= 4 for im in images[:2]):
                    return InputError(f"{base}: no {spec.dictionary} markers were detected, but {name} markers "
                                      f"were; fix 'dictionary' in board.yaml")
            except cv2.error:
                continue
        return InputError(f"{base}: no {spec.dictionary} markers were detected at all; check 'dictionary' "
                          "and that the images show the board sharply")
    # the board type's fields are set (parse_board)
    n_markers = spec.squares[0] * spec.squares[1] // 2  # type: ignore[index]
    if markers.max() >= n_markers:
        return InputError(f"{base}: markers with ids up to {int(markers.max())} were seen but a "
                          # the board type's fields are set (parse_board)
                          f"{spec.squares[0]}x{spec.squares[1]} board has ids 0..{n_markers - 1}; fix 'squares'")  # type: ignore[index]
    legacy = BoardSpec(**{**spec.__dict__, "legacy_pattern": not spec.legacy_pattern})
    if any(BoardDetector(legacy).detect(im) is not None for im in images):
        return InputError(f"{base}: {spec.dictionary} markers were detected and the corners match with "
                          f"legacy_pattern: {str(legacy.legacy_pattern).lower()}; set that in board.yaml")
    return InputError(f"{base}: {len(markers)} {spec.dictionary} markers were detected but no ChArUco corners "
                      "could be interpolated; check 'squares', 'square' and 'marker' in board.yaml")
