"""``rigsfm explore``: check a finished result on people you can recognise, and label correspondences.

Library use: ``start_explorer(OUT, ExploreOptions(...)) -> ExploreServer`` (``url``, ``close()``);
``check_labels(OUT, labels.csv) -> CheckResult`` (the share of labelled pairs inside their band).
"""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "ExploreOptions": "rigsfm.explore.session",
    "ExploreSession": "rigsfm.explore.session",
    "check_labels": "rigsfm.explore.session",
    "parse_heights": "rigsfm.explore.session",
    "ExploreServer": "rigsfm.explore.server",
    "start_explorer": "rigsfm.explore.server",
})
