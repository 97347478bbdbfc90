"""Sanity checks of a finished reconstruction that a user cannot see in reprojection errors.

- Rigidity: with three or more rigs, the images fix the relative distances between rigs only through
  tracks seen by three or more rigs. Rigs linked to the rest by two-view tracks alone can slide along
  their viewing directions (a 4-rig circle 90 degrees apart is the classic case): the model still
  reprojects well while its shape is wrong.
- Scale consistency: several scale measurements must agree within their uncertainties; when they do
  not, the shape of the model (or a measurement) is wrong.
"""

from __future__ import annotations

import pycolmap

from rigsfm.scale import ScaleEstimate

MIN_SHARED_POINTS = 20  # three-view points that tie a rig to the others
MAX_NORMALISED_RESIDUAL = 5.0


def loosely_tied_rigs(reconstruction: pycolmap.Reconstruction) -> list[str]:
    """Rigs not tied to the largest group of rigs by points seen from at least three rigs."""
    rig_of_image = {image.image_id: image.name.split("/", 1)[0]
                    for image in reconstruction.images.values() if image.has_pose}
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
    parent = {rig: rig for rig in rigs}

    def root(rig: str) -> str:
        while parent[rig] != rig:
            parent[rig] = parent[parent[rig]]
            rig = parent[rig]
        return rig

    for (a, b), count in shared.items():
        if count >= MIN_SHARED_POINTS:
            parent[root(a)] = root(b)
    groups: dict[str, list[str]] = {}
    for rig in rigs:
        groups.setdefault(root(rig), []).append(rig)
    largest = max(groups.values(), key=len)
    if len(largest) < 3:  # no rigid core at all
        return rigs
    return sorted(rig for rig in rigs if rig not in largest)


def check_reconstruction(reconstruction: pycolmap.Reconstruction, scale: ScaleEstimate | None) -> list[str]:
    """Warnings (empty when the checks pass)."""
    warnings = []
    loose = loosely_tied_rigs(reconstruction)
    if loose:
        warnings.append(
            f"SHAPE NOT DETERMINED: {', '.join(loose)} share no points with two other rigs, so their distances "
            "to the rest are not fixed by the images and may be wrong; add rigs in between or wider views, "
            "and check against scale.yaml measurements"
        )
    if scale is not None and len(scale.measurements) > 1:
        for row in scale.residuals():
            if abs(row["residual_meters"]) > MAX_NORMALISED_RESIDUAL * row["sigma_meters"]:
                warnings.append(
                    f"SCALE MEASUREMENTS DISAGREE: {row['label']} is {row['reconstructed_meters']:.4f} m in the model "
                    f"but measured {row['meters']:.4f} m ({row['residual_percent']:+.2f} %, more than "
                    f"{MAX_NORMALISED_RESIDUAL:g} sigma); the model's shape or that measurement is wrong"
                )
    return warnings
