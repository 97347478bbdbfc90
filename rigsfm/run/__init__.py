"""``rigsfm run``: metric poses of every narrow camera of a hybrid-rig network, from image folders.

Library use: ``run(IMAGES, rigs.yaml, OUT, scale.yaml, RunOptions(...)) -> RunResult``.

The stages, in pipeline order (:func:`rigsfm.run.pipeline.run` calls them):

1. ``inputs``, ``scale_file``, ``manual_matches`` — validate every input before any heavy work;
2. ``database`` — calibrated cameras, images, the rig configuration with E^sl;
3. ``features`` (``asift``) — features and verified matches; ``manual_merge`` adds hand-picked ones;
4. ``mapping`` — COLMAP's incremental or global mapper on the wide images;
5. ``adjust`` (``scale``) — the metric bundle adjustment with the rigs' calibration;
5b. ``world`` (``floor``, ``floor_matching``) — the floor frame: z = 0 on the floor, z up, metres; ground maps;
6. ``uncertainty``, ``diagnostics`` — what the result is worth, and warnings;
7. ``deliver`` — sparse/, narrow_poses.json, points3D.ply; ``self_check`` — epipolar distances of matches
   between synchronised narrow images against the band; ``summary`` — summary.json.
"""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "run": "rigsfm.run.pipeline",
    "load_inputs": "rigsfm.run.pipeline",
    "RunResult": "rigsfm.run.pipeline",
    "RunOptions": "rigsfm.run.options",
    "MatchingOptions": "rigsfm.run.options",
    "MappingOptions": "rigsfm.run.options",
    "AdjustOptions": "rigsfm.run.options",
    "Features": "rigsfm.run.options",
    "Mapper": "rigsfm.run.options",
    "WorldFrame": "rigsfm.run.options",
    "WorldOptions": "rigsfm.run.options",
    "SelfCheckOptions": "rigsfm.run.options",
    "Summary": "rigsfm.core.summary",
})
