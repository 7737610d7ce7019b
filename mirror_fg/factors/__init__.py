"""Source-tree alias of the top-level ``factors/`` folder (the custom GTSAM factors).

An installed wheel ships ``factors/`` itself as ``mirror_fg.factors`` (pyproject's package-dir), so
this file is not installed; in a checkout it lets ``import mirror_fg`` work from the repository root.
"""
import os as _os

__path__ = [_os.path.join(_os.path.dirname(_os.path.dirname(_os.path.dirname(_os.path.abspath(__file__)))), "factors")]
