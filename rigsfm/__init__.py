"""rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks with COLMAP 4."""

from rigsfm.core.errors import InputError, ReconstructionError, RigsfmError, WorkspaceError

__version__ = "0.1.0"
__all__ = ["InputError", "ReconstructionError", "RigsfmError", "WorkspaceError", "__version__"]
