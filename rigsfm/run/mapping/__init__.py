"""Stage 5, mapping: COLMAP's incremental or global mapper on the wide images, and how rigidly it ties the rigs."""
