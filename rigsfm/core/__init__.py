"""The shared core every verb builds on: the rig model and its files, convention conversions, geometry,
the output workspace, atomic writes and the error family. Nothing here imports a verb."""
