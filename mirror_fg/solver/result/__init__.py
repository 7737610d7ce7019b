"""The result of a solve: ``Calibration`` (calibration.py), its one builder, the checks before it is
written, and the error it implies at a point of the user's choosing."""
