"""Look at a finished run: ``report`` (report.html), ``viewer`` (Open3D) and ``export`` (other tools' formats)."""
