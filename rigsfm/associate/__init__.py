"""Association of point detections (heads) across synchronised narrow cameras into 3D persons.

``associate(OUT, DETECTIONS, AssociateOptions(...))`` reads a finished run and a detections CSV and writes DIR
(rigsfm.associate.output); ``associate_frames`` returns the persons without writing anything.
"""

from rigsfm.associate.detections import Detections, from_arrays, read_detections
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.pipeline import associate, associate_frames, load_run
from rigsfm.associate.solve import FrameResult

__all__ = ["AssociateOptions", "Detections", "FrameResult", "associate", "associate_frames", "from_arrays",
           "load_run", "read_detections"]
