"""Options of ``rigsfm associate`` (kw-only, typed; the CLI maps its flags onto these)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from rigsfm.associate.rates import Occlusion


@dataclass(frozen=True, kw_only=True)
class AssociateOptions:
    heights: tuple[float, float] = (1.0, 2.1)  # metres above the floor where the points (heads) may lie
    # The detector's noise per coordinate (px), added to each view's band; None: the crowd's (a first frame
    # associated again with the noise its confident persons show, rigsfm.associate.solve.associate_views).
    pixel_sigma: float | None = None
    # A person's point is detected in a view that sees it (occlusion included); None: estimated from the frame's
    # persons (rigsfm.associate.rates), starting from 0.7.
    detection_probability: float | None = None
    # Mean and sigma (m) of the points' heights, the score's prior over height inside ``heights``; None: estimated
    # from the frame's confident persons (uniform over ``heights`` until there are enough).
    height_prior: tuple[float, float] | None = None
    # Each view's detection probability from the crowd's occlusion (rates.Occlusion: persons in front of a point
    # hide it, so a view that hides it is no miss); False: ``detection_probability`` in every view. ``occlusion``:
    # the model, None: fitted from a self-calibrating frame's persons with the rates; not carried (a carried frame
    # counts one probability for every view: with it, a third of its CPU, benchmarks/README.md).
    visibility: bool = True
    occlusion: Occlusion | None = None
    # The detections' apparent head radii (px; the DETECTIONS' radius column) as evidence of depth, used where every
    # detection of a frame has one: a radius is f R / distance, R the person's head radius. ``size_noise``: the
    # detector's relative (log) error of a radius; ``head_radius_spread``: the persons' relative spread of R;
    # ``head_radius_m``: the crowd's mean R, None: estimated from the frame's confident persons (starting at 0.1 m,
    # 30 % uncertain).
    size_noise: float = 0.1
    head_radius_spread: float = 0.1
    head_radius_m: float | None = None
    persons_per_m2: float = 2.0  # the prior density of persons on the floor (the score's price of a new person)
    clutter_radius_px: float = 40.0  # the local density of detections (chance matches) is counted within this
    gate_sigmas: float = 3.5  # candidate pairs: distance to i's ray segment in j within this many sigmas
    member_gate: float = 3.5  # a member's reprojection within this many sigmas of the person's point
    min_score: float = -2.0  # keep hypotheses whose score exceeds this (measured best on rendered crowds)
    # In a carried frame (associate_frames' later frames), a pair seed grows into other views only where its own
    # score, its misses left out, exceeds this (the chance pairs of a crowd's bands, most of the seeds, grow into
    # nothing the packing keeps); None: every seed grows. A first frame grows every seed.
    seed_min_score: float | None = -4.0
    # A carried frame first looks for each of the frame before's persons around its point (a person walks this far
    # per floor axis between two frames, 1 sigma: m), and searches the pairs only among the detections its confident
    # persons leave; None: every pair searched, as in a first frame.
    walk_m: float | None = 0.15
    # Associate again among the detections the packing left free, each hypothesis re-scored against the free
    # detections' density (persons seen in two views only).
    second_pass: bool = True
    # The crowd corrects each view's pose error: associate, estimate every view's shift from the groups of three or
    # more views scoring above this, associate again with the shifted views (at most this many rounds, fewer once the
    # confident groups stop growing; 0: the run's poses).
    self_calibration_rounds: int = 4
    self_calibration_min_score: float = 0.0
    self_calibration_min_members: int = 10  # a view's shift needs this many group members (else it stays as run)
    # A frame whose crowd corrected none of its views is associated again, carried, with the shifts a later frame's
    # crowd found for its cameras (the recording's, pooled over the frames since).
    revisit: bool = True
    # Add the heads' and torsos' greys to the score where the run's narrow images can be read (rigsfm.associate.
    # appearance): its model comes from the frame's own confident persons.
    appearance: bool = True
    time_limit_s: float = 20.0  # per frame, for the global set packing (then the best solution found)
    cell_m: float = 1.0  # density grid cell (m)
    # A frame of the run whose narrow cameras' poses (and bands) stand in for frames the run was not given: static
    # rigs, associated frame after frame of a recording calibrated once. None: every frame must be one of the run's.
    poses_from: str | None = None
    # Whether the rigs took their frames together (rigsfm.associate.sync): None checks a recording of three frames or
    # more and warns of a rig off in time; "auto" also pairs the frames by the offsets it names; "off" skips the
    # check; else a file of offsets ('rig03: 1', rigsfm run --frame-offsets FILE's) to pair them by.
    frame_offsets: str | Path | None = None
    out: Path | None = None  # DIR; None: OUT/associate
    overwrite: bool = False

    @property
    def view_occlusion(self) -> Occlusion | None:
        """The occlusion model the score uses: ``occlusion`` where ``visibility`` is on, else None."""
        return self.occlusion if self.visibility else None

    def __post_init__(self) -> None:
        lo, hi = self.heights
        if not (lo < hi):
            raise ValueError(f"heights must be two increasing numbers (m), got {lo}, {hi}")
        if self.pixel_sigma is not None and not (self.pixel_sigma > 0 and math.isfinite(self.pixel_sigma)):
            raise ValueError(f"pixel sigma must be > 0 px, got {self.pixel_sigma}")
        if self.detection_probability is not None and not 0 < self.detection_probability < 1:
            raise ValueError(f"detection probability must be in (0, 1), got {self.detection_probability}")
        if self.height_prior is not None and not self.height_prior[1] > 0:
            raise ValueError(f"the height prior's sigma must be > 0 m, got {self.height_prior[1]}")
        if not (self.size_noise > 0 and self.head_radius_spread > 0 and math.isfinite(self.size_noise)
                and math.isfinite(self.head_radius_spread)):
            raise ValueError(f"size noise and head radius spread must be finite and > 0, got {self.size_noise}, "
                             f"{self.head_radius_spread}")
        if self.head_radius_m is not None and not (0 < self.head_radius_m < 1):
            raise ValueError(f"the head radius must be in (0, 1) m, got {self.head_radius_m}")
        if self.seed_min_score is not None and not math.isfinite(self.seed_min_score):
            raise ValueError(f"the seeds' minimum score must be a finite number or None, got {self.seed_min_score}")
        if self.walk_m is not None and not (self.walk_m > 0 and math.isfinite(self.walk_m)):
            raise ValueError(f"the walk between frames must be a finite number > 0 m or None, got {self.walk_m}")
        if not (self.gate_sigmas > 0 and self.member_gate > 0 and self.cell_m > 0 and self.time_limit_s > 0
                and self.persons_per_m2 > 0):
            raise ValueError("gates, cell size and time limit must be > 0")
        if self.self_calibration_rounds < 0 or self.self_calibration_min_members < 1:
            raise ValueError("self-calibration rounds must be >= 0 and its minimum members >= 1")
