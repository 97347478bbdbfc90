"""``rigsfm track``: re-estimate rig poses over time against a reference run (shake and drift monitoring).

Library use: ``track(OUT, NEW_IMAGES, TrackOptions(...)) -> TrackResult`` (``rigsfm.track.pipeline``).
"""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "track": "rigsfm.track.pipeline",
    "TrackResult": "rigsfm.track.pipeline",
    "TrackOptions": "rigsfm.track.options",
    "Thresholds": "rigsfm.track.options",
    "RegistrationOptions": "rigsfm.track.options",
    "Executor": "rigsfm.track.options",
    "Verdict": "rigsfm.track.verdict",
    "classify": "rigsfm.track.verdict",
    "ReferenceMap": "rigsfm.track.reference",
    "load_reference": "rigsfm.track.reference",
    "FrameTask": "rigsfm.track.register",
    "register_frame": "rigsfm.track.register",
    "track_report_section": "rigsfm.track.report",
})
