"""Imported last by the forkserver of :mod:`rigsfm.core.stages`, only there.

pycolmap's import installs glog's failure handler for SIGTERM, which prints a C stack trace; a forkserver
terminated with its process group (systemd, Slurm) should just end, as it would without pycolmap.
"""

import signal

signal.signal(signal.SIGTERM, signal.SIG_DFL)
