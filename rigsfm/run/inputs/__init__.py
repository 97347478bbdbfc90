"""Stages 1-2, validate and database: every input checked before any heavy work (the image folder, scale.yaml;
hand-picked matches in ``matching.manual_matches``), then the COLMAP database."""
