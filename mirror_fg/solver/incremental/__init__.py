"""iSAM2: the estimate as images arrive. ``calibrator.py`` holds the state and a backend (``tree.py`` for
the paper's tree on ``graph.py``; ``views.py`` for any views).

The calibrator's names are also here: ``from mirror_fg.solver.incremental import IncrementalCalibrator``."""


def __getattr__(name: str):
    import importlib

    calibrator = importlib.import_module("mirror_fg.solver.incremental.calibrator")
    try:
        return getattr(calibrator, name)
    except AttributeError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
