"""Stage 4: COLMAP's incremental or global mapper on the wide images."""
