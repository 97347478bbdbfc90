"""The one image-name type: ``<rig>/<sensor>/<frame file>``, as under IMAGES/ and in every COLMAP model rigsfm
writes. Parse a name with :meth:`ImageName.parse` (or :func:`of` for a ``pycolmap.Image``), build one with
``ImageName(rig, sensor, frame)`` and ``str()``. A frame is a file name: images of one rig with the same frame
name were taken at the same instant."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Sensor(enum.StrEnum):
    WIDE = "wide"  # short focal length: the surroundings, used for registration (the rig's reference sensor)
    NARROW = "narrow"  # long focal length: the homogeneous area, used for analysis


SENSORS = (Sensor.WIDE, Sensor.NARROW)


@dataclass(frozen=True, order=True)
class ImageName:
    rig: str
    sensor: Sensor
    frame: str

    @classmethod
    def parse(cls, name: str) -> ImageName:
        """``"rig01/narrow/f0.png"`` -> ``ImageName("rig01", Sensor.NARROW, "f0.png")``; ValueError otherwise."""
        parts = str(name).split("/", 2)
        if len(parts) != 3 or not all(parts) or parts[1] not in {s.value for s in SENSORS}:
            raise ValueError(f"{name!r} is not an image name <rig>/<wide|narrow>/<frame file>")
        return cls(parts[0], Sensor(parts[1]), parts[2])

    @property
    def camera(self) -> str:
        """``<rig>/<sensor>``: the camera the image was taken with."""
        return f"{self.rig}/{self.sensor}"

    @property
    def is_narrow(self) -> bool:
        return self.sensor == Sensor.NARROW

    def __str__(self) -> str:
        return f"{self.rig}/{self.sensor}/{self.frame}"


def name_of(image) -> ImageName:
    """The parsed name of a ``pycolmap.Image`` (or anything with a ``name``)."""
    return ImageName.parse(image.name)


def registered_narrow_images(reconstruction) -> list:
    """The registered narrow images of a ``pycolmap.Reconstruction``, sorted by name."""
    return sorted((im for im in reconstruction.images.values() if im.has_pose and name_of(im).is_narrow),
                  key=lambda im: im.name)


def quoted(names) -> str:
    """Names as messages show them: each in single quotes, so that one with spaces or brackets reads as one
    (``'rig 01', 'rig[2]'``)."""
    return ", ".join(f"'{name}'" for name in names)
