"""``rigsfm run``: metric poses of every narrow camera of a hybrid-rig network, from image folders.

The stages, in pipeline order (:func:`rigsfm.run.pipeline.run` calls them):

1. ``inputs``, ``scale_file``, ``manual_matches`` — validate every input before any heavy work;
2. ``database`` — calibrated cameras, images, the rig configuration with E^sl;
3. ``features`` (``asift``) — features and verified matches; ``manual_merge`` adds hand-picked ones;
4. ``mapping`` — COLMAP's incremental or global mapper on the wide images;
5. ``adjust`` (``scale``) — the metric bundle adjustment with the rigs' calibration;
6. ``uncertainty``, ``diagnostics`` — what the result is worth, and warnings;
7. ``deliver`` — sparse/, narrow_poses.json, points3D.ply, summary.json.
"""
