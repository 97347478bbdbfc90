"""report.html: ``write_report(OUT) -> Path`` (``rigsfm.inspect.report.write``)."""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {"write_report": "rigsfm.inspect.report.write",
                                               "load_result": "rigsfm.inspect.report.write"})
