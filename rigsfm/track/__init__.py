"""``rigsfm track``: re-estimate rig poses over time against a reference run (shake and drift monitoring)."""

from rigsfm.track.command import TrackResult, track, track_command
from rigsfm.track.verdict import Thresholds, Verdict, classify
from rigsfm.track.pose import RegistrationOptions
from rigsfm.track.reference import ReferenceMap, load_reference
from rigsfm.track.register import FrameTask, register_frame
from rigsfm.track.report import track_report_section

__all__ = [
    "FrameTask",
    "ReferenceMap",
    "RegistrationOptions",
    "Thresholds",
    "TrackResult",
    "Verdict",
    "classify",
    "load_reference",
    "register_frame",
    "track",
    "track_command",
    "track_report_section",
]
