"""``rigsfm run``: metric poses of every narrow camera of a hybrid-rig network, from image folders.

Library use: ``run(IMAGES, rigs.yaml, OUT, scale.yaml, RunOptions(...)) -> RunResult``.

The stages, in pipeline order (:func:`rigsfm.run.pipeline.run` calls them; each is timed under its name in
summary.json's ``timings_s``), over the sub-packages that hold them:

1. ``validate`` -- ``inputs.images``, ``inputs.scale_file``, ``matching.manual_matches``: every input checked first;
2. ``database`` -- ``inputs.database``: calibrated cameras, images, the rig configuration with E^sl;
3. ``features`` -- ``matching.extract`` (``reuse``, ``feature_cache``, ``asift``, ``gpu``);
4. ``matching`` -- ``matching.pairs``, ``matching.match``; ``manual_matches``: ``matching.manual_merge``;
5. ``mapping`` -- ``mapping.mapper`` (``mapping.ties``): COLMAP's incremental or global mapper on the wide images;
6. ``adjust`` -- ``adjustment.adjust`` (``problem``, ``priors``, ``costs``, ``scale``, ``decisions``): the metric
   bundle adjustment with the rigs' calibration;
7. ``world`` -- ``world.frame`` (``floor``, ``floor_fit``, ``floor_matching``, ``analysis_floor``): the floor frame;
8. ``uncertainty`` -- ``adjustment.uncertainty`` (``covariance``, ``narrow``, ``bands``, ``sampled``); with narrow
   observations ``narrow_observations``, ``uncertainty_final`` and ``world_refit`` (the floor fitted again on the
   model adjusted again);
9. ``deliver`` -- ``world.floor_poses`` (the poses' covariance carried into the floor's sigma), ``deliver``: sparse/,
   narrow_poses.json, points3D.ply; summary.json (``rigsfm.core.summary``)
   with ``checks.diagnostics``' warnings;
10. ``check_pairs`` -- ``checks.missed_pairs``: skipped pairs the model says would have shared many points;
11. ``self_check`` -- ``checks.self_check`` (``guided``, ``sync``): epipolar distances of matches between
    synchronised narrow images against the band.
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
