"""Look at a finished run: ``write_report`` (report.html), ``screenshot``/``show`` (Open3D) and ``export``
(other tools' formats)."""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "write_report": "rigsfm.inspect.report.write",
    "export": "rigsfm.inspect.export",
    "ExportFormat": "rigsfm.inspect.options",
    "ExportOptions": "rigsfm.inspect.options",
    "screenshot": "rigsfm.inspect.viewer",
    "show": "rigsfm.inspect.viewer",
})
