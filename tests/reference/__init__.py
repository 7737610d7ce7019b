"""The paper's tree in its own factors: the independent reference the one measurement model (the view
factors of ``factors/``) is checked against, kept with the tests and the benchmarks that compare the two.

``model.py`` (eqs. 2, 3, 9 vectorised over measurements), ``reflection.py`` (one factor per measurement),
``batched.py`` (stacked), ``eliminated.py`` (the last mirror's placements eliminated inside the factors),
``intrinsics_factors.py`` (pixels through estimated intrinsics), ``stacking.py`` (their grouping),
``graph.py`` (the tree's factor graphs), ``marginals.py`` (their covariances) and ``lm.py`` (a calibration
on them: :func:`lm.use_tree_factors`).
"""
