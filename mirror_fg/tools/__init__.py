"""Empty: its modules moved (``pattern.py`` to ``vision/``, ``many.py`` to ``analysis/``); their old import
paths still import for one release (``mirror_fg/_moved.py``)."""
