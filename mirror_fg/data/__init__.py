"""The values a calibration reads and returns, without parsing or solving: :class:`Dataset` and
:class:`Image` (what was observed; read and written by :mod:`mirror_fg.io.dataset`), :class:`Calibration`
and its parts (what was estimated; written by :mod:`mirror_fg.io.result`, built by
:mod:`mirror_fg.solver.result.builder`)."""
from mirror_fg.data.calibration import CameraPose, Calibration, EstimatedCamera, Exclusion, Inconsistency
from mirror_fg.data.dataset import Dataset, Image, Scale

__all__ = ["Dataset", "Image", "Scale", "Calibration", "CameraPose", "EstimatedCamera", "Exclusion", "Inconsistency"]
