"""Rigidity of the mapped network: with three or more rigs, the images fix the relative distances between rigs only
through tracks seen by three or more rigs; rigs linked to the rest by two-view tracks alone can slide along their
viewing directions while the model still reprojects well."""

from __future__ import annotations

from collections.abc import Iterable

import pycolmap

from rigsfm.core.graph import DisjointSets
from rigsfm.core.names import name_of

MIN_SHARED_POINTS = 20  # three-view points that tie a rig to the others


def rig_of(image: pycolmap.Image) -> str:
    return name_of(image).rig


def loosely_tied_rigs(reconstruction: pycolmap.Reconstruction) -> list[str]:
    """Rigs not tied to the largest group of rigs by points seen from at least three rigs."""
    rig_of_image = {image.image_id: rig_of(image) for image in reconstruction.images.values() if image.has_pose}
    rigs = sorted(set(rig_of_image.values()))
    if len(rigs) < 3:
        return []
    shared: dict[tuple[str, str], int] = {}
    for point in reconstruction.points3D.values():
        seen = sorted({rig_of_image[e.image_id] for e in point.track.elements if e.image_id in rig_of_image})
        if len(seen) < 3:
            continue
        for i, a in enumerate(seen):
            for b in seen[i + 1:]:
                shared[(a, b)] = shared.get((a, b), 0) + 1
    largest = max(rig_groups(rigs, [pair for pair, count in shared.items() if count >= MIN_SHARED_POINTS]), key=len)
    if len(largest) < 3:  # no rigid core at all
        return rigs
    return sorted(rig for rig in rigs if rig not in largest)


def rig_groups(rigs: list[str], links: Iterable[tuple[str, str]]) -> list[list[str]]:
    """Connected components of the rigs under ``links``."""
    sets = DisjointSets(rigs)
    for a, b in links:
        sets.union(a, b)
    return sets.groups()
