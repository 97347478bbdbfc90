"""The options of a synthetic dataset (``SceneOptions``): what the arena, the rigs, the crowd and the images are."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneOptions:
    """Everything that defines a synthetic dataset; same options + seed -> identical dataset."""

    num_rigs: int = 8
    arc_deg: float = 360.0  # total angular span of the rigs; 360 = full circle
    radius: float = 15.0  # rig circle radius (m)
    image_scale: float = 1.0  # 0.5 -> 812x617 images, intrinsics scaled accordingly
    seed: int = 0
    textured_centre: bool = False
    calibration_noise: bool = True
    frames_per_rig: int = 1
    rig_height: float = 3.5  # mean wide-camera height (m); each rig varies by +-0.25 m
    wide_pitch_deg: float = 12.0  # wide camera looks this much below the horizon
    narrow_extra_pitch_deg: float = 10.0  # narrow camera looks this much further down
    baseline: float = 0.06  # wide-narrow camera centre distance (m)
    width: int = 1624
    height: int = 1234
    wide_focal: float = 900.0  # px at full size (4 mm lens, 4.4 um pixels)
    narrow_focal: float = 3600.0  # px at full size (16 mm lens)
    wall_radius: float = 28.0
    wall_height: float = 16.0
    centre_radius: float = 11.0  # homogeneous disc radius (m)
    num_pillars: int = 6
    num_boxes: int = 5
    bar_length: float = 2.0
    noise_sigma: float = 1.5  # grey levels
    vignetting: float = 0.12  # relative darkening at the image corners
    persons_per_m2: float = 0.0  # 3D persons on the centre disc (rigsfm.synth.persons); 0: none
    person_separation: float = 0.4  # least distance between two persons' centres (m)
    frame_period_s: float = 0.5  # time between two frames of a rig (persons walk meanwhile)
    frame_offsets: tuple[tuple[str, float], ...] = ()  # (rig, frames): its frame k is taken at time k + offset
    exposure_jitter: float = 0.0  # each image's exposure gain is uniform in 1 +- this
    jpeg_quality: int = 0  # 1..100: JPEG images of that quality; 0: PNG

    def __post_init__(self) -> None:
        if self.num_rigs < 2:
            raise ValueError(f"num_rigs must be >= 2, got {self.num_rigs}")
        if not 0.0 < self.arc_deg <= 360.0:
            raise ValueError(f"arc_deg must be in (0, 360], got {self.arc_deg}")
        if not 0.05 <= self.image_scale <= 2.0:
            raise ValueError(f"image_scale must be in [0.05, 2], got {self.image_scale}")
        if self.frames_per_rig < 1:
            raise ValueError(f"frames_per_rig must be >= 1, got {self.frames_per_rig}")
        if not self.centre_radius + 1.0 < self.radius < self.wall_radius - 4.0:
            raise ValueError("need centre_radius + 1 < radius < wall_radius - 4")
        if self.persons_per_m2 < 0 or self.person_separation <= 0 or self.frame_period_s <= 0:
            raise ValueError("persons_per_m2 must be >= 0, person_separation and frame_period_s > 0")
        if not 0.0 <= self.exposure_jitter < 1.0:
            raise ValueError(f"exposure_jitter must be in [0, 1), got {self.exposure_jitter}")
        if not 0 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 1..100 (0: PNG), got {self.jpeg_quality}")
        rigs = {f"rig{i + 1:02d}" for i in range(self.num_rigs)}
        unknown = sorted(name for name, _ in self.frame_offsets if name not in rigs)
        if unknown:
            raise ValueError(f"frame offsets name unknown rigs {', '.join(unknown)} "
                             f"(rigs are rig01..rig{self.num_rigs:02d})")

    def frame_offset(self, rig: str) -> float:
        """Rig ``rig``'s frame k is taken at time ``(k + offset) * frame_period_s``."""
        return dict(self.frame_offsets).get(rig, 0.0)
