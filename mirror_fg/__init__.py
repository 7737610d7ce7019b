"""mirror_fg: camera-to-base calibration through multiple planar mirrors (Hesch et al., ECCV 2010)."""
