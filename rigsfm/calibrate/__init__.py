"""``rigsfm calibrate``: intrinsics of both cameras of each rig and E^sl from calibration-board images.

Library use::

    from rigsfm.calibrate import CalibrateOptions, calibrate
    result, rigs_yaml, report = calibrate(Path("BOARD"), Path("rigs.yaml"), CalibrateOptions(board=Path("board.yaml")))

or, step by step: ``calibrate_rigs(BOARD, load_board_spec(board.yaml))`` then ``write_calibration(result, out)``.
The steps per rig are in ``rigsfm.calibrate.pipeline``.
"""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "calibrate": "rigsfm.calibrate.pipeline",
    "calibrate_rig": "rigsfm.calibrate.pipeline",
    "calibrate_rigs": "rigsfm.calibrate.pipeline",
    "write_calibration": "rigsfm.calibrate.pipeline",
    "CalibrationResult": "rigsfm.calibrate.results",
    "RigResult": "rigsfm.calibrate.results",
    "CalibrateOptions": "rigsfm.calibrate.options",
    "Distortion": "rigsfm.calibrate.options",
    "BoardSpec": "rigsfm.calibrate.board",
    "load_board_spec": "rigsfm.calibrate.board",
})
