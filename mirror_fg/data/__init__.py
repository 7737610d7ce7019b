"""The values a calibration reads, without parsing or solving: :class:`Dataset` and :class:`Image` (what was
observed; read and written by :mod:`mirror_fg.io.dataset`). The result, :class:`~mirror_fg.solver.result.calibration.Calibration`,
stays with the solver: its methods (``point_error``, ``to_dict``) use the solver and the result's writer."""
from mirror_fg.data.dataset import Dataset, Image, Scale

__all__ = ["Dataset", "Image", "Scale"]
