"""Features reused across workspaces: with ``RIGSFM_FEATURE_CACHE=DIR`` in the environment, every image's extracted
keypoints and descriptors are also kept in DIR, and a later extraction of the same image file with the same
settings, in any workspace and any process, reads them back instead of extracting again.

An entry's key is the SHA-256 of the image file's bytes and of everything the features depend on: the extractor
and its options (threads left out), pycolmap's and OpenCV's versions. What is read back is what was written to
the first workspace's database, so a hit is bit-identical to an extraction. Entries are written atomically
(whole or absent for a process reading meanwhile); an unreadable one is extracted again and replaced.

For repeated runs on the same images into new output folders (the test suite sets it: its scenes are run by
many tests; benchmarks comparing methods on one scene). Off by default; a workspace's own database already keeps
its features for a re-run of that workspace.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.io import file_sha256, read_npz, write_npz_atomic

logger = logging.getLogger(__name__)

FEATURE_CACHE_ENV = "RIGSFM_FEATURE_CACHE"


@dataclass(frozen=True)
class FeatureCache:
    """DIR of ``RIGSFM_FEATURE_CACHE`` and the settings every entry made here depends on."""

    folder: Path
    settings: str  # canonical JSON

    @classmethod
    def from_environment(cls, settings: dict) -> FeatureCache | None:
        folder = os.environ.get(FEATURE_CACHE_ENV)
        if not folder:
            return None
        versions = {"pycolmap": pycolmap.__version__, "opencv": cv2.__version__}
        return cls(Path(folder), json.dumps({**settings, "versions": versions}, sort_keys=True, default=str))

    def entry(self, image: Path) -> Path:
        """Where the features of ``image`` (its file's bytes with these settings) are kept."""
        return self.folder / f"{file_sha256(image, self.settings.encode())}.npz"

    @staticmethod
    def load(entry: Path) -> tuple[np.ndarray, np.ndarray] | None:
        """``(keypoints (N, 6) float32, descriptors (N, 128) uint8)`` kept in ``entry``, or None."""
        arrays = read_npz(entry)  # None: not stored yet, or unreadable
        if arrays is None or set(arrays) != {"keypoints", "descriptors"}:
            return None
        keypoints, descriptors = arrays["keypoints"], arrays["descriptors"]
        if (keypoints.dtype != np.float32 or keypoints.ndim != 2 or keypoints.shape[1] != 6
                or descriptors.dtype != np.uint8 or descriptors.shape != (len(keypoints), 128)):
            return None
        return keypoints, descriptors

    @staticmethod
    def store(entry: Path, keypoints: np.ndarray, descriptors: np.ndarray) -> None:
        """Adds an entry; a cache that cannot be written (full, read-only) is only a warning."""
        arrays = {"keypoints": np.asarray(keypoints, np.float32), "descriptors": np.asarray(descriptors, np.uint8)}
        try:
            write_npz_atomic(entry, arrays)
        except OSError as error:
            logger.warning("Feature cache entry %s not written (%s): these features are not kept", entry,
                           error.strerror or error)


def features_from_cache(database: pycolmap.Database, cache: FeatureCache, entries: dict[str, Path],
                        ids: dict[str, int]) -> list[str]:
    """Writes the cached features of the images of ``entries`` (name -> :meth:`FeatureCache.entry`) into
    ``database``; returns the names still to extract."""
    missing = []
    for name, entry in entries.items():
        found = cache.load(entry)
        if found is None:
            missing.append(name)
            continue
        keypoints, descriptors = found
        with pycolmap.DatabaseTransaction(database):
            database.write_keypoints(ids[name], keypoints)
            database.write_descriptors(
                ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, descriptors))
    if len(missing) < len(entries):
        logger.info("Features of %d images read from the feature cache %s", len(entries) - len(missing),
                    cache.folder)
    return missing


def features_to_cache(database: pycolmap.Database, cache: FeatureCache, entries: dict[str, Path],
                      ids: dict[str, int], names: list[str]) -> None:
    """Stores the features ``database`` holds for ``names`` (just extracted) in their ``entries``."""
    for name in names:
        if database.exists_keypoints(ids[name]):
            cache.store(entries[name], database.read_keypoints(ids[name]), database.read_descriptors(ids[name]).data)
