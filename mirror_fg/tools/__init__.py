"""Commands' engines that are neither solver nor analysis: ``mirror-fg pattern`` and ``calibrate-many``."""
