"""File formats, each with one reader and one writer (docs/formats.md): dataset@1, result@1, capture@1,
camera calibration files, ROS/URDF outputs; and bounded, all-or-nothing file access (fileio)."""
