"""rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks with COLMAP 4.

The verbs, each a plain function with typed options (see each package's docstring):
``rigsfm.calibrate.calibrate``, ``rigsfm.run.run``, ``rigsfm.inspect.write_report`` / ``export`` /
``screenshot``, ``rigsfm.pick.start_picker``, ``rigsfm.track.track``; ``rigsfm.synth`` renders test scenes.
"""

from rigsfm.core.errors import InputError, ReconstructionError, RigsfmError, WorkspaceError

__version__ = "0.2.0"
__all__ = ["InputError", "ReconstructionError", "RigsfmError", "WorkspaceError", "__version__"]
