"""Typed options of ``rigsfm export`` and ``rigsfm view``; imports nothing heavy."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path


class ExportFormat(enum.StrEnum):
    COLMAP_BIN = "colmap-bin"  # COLMAP model, binary (COLMAP >= 3.8 reads it)
    COLMAP_TXT = "colmap-txt"  # COLMAP model, text
    OPEN3D = "open3d"  # points.ply, frustums.ply, trajectory.json
    NERFSTUDIO = "nerfstudio"  # transforms.json
    JSON = "json"  # poses.json: every image's camera and cam_from_world
    OPENCV = "opencv"  # intri.yml / extri.yml: OpenCV FileStorage YAML in EasyMocap's layout
    TOML = "toml"  # calibration.toml in aniposelib's layout (also read by Caliscope)
    WILDTRACK = "wildtrack"  # calibrations/intrinsic_zero, extrinsic: WILDTRACK / MVDet's layout, centimetres


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    format: ExportFormat
    dest: Path | None = None  # default OUT/export/<format>
    overwrite: bool = False  # replace an earlier export of rigsfm in dest (nothing else is ever removed)
    images: bool = False  # wildtrack: also the narrow images, undistorted (Image_subsets/)
    # with images: also the narrow images beside the run's of frames it was not given (a recording, as
    # `rigsfm associate --poses-from`), undistorted with the cameras of its frame poses_from (static rigs)
    poses_from: str | None = None
