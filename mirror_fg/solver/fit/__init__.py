"""How well a result fits and predicts: the image-level dispersion stored by calibrate and the
held-out validation (``--validate``)."""
