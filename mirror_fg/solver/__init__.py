"""The solver: ``calibrate()`` (calibrate.py) runs one problem through the pipeline (pipeline.py): screen
(screen/), analytical start (start/), Levenberg-Marquardt on the factor graph (model/, factors/),
marginals, final check, result (result/); iSAM2 as images arrive (incremental/); the fit's dispersion
and held-out validation (fit/); Fisher information and Cramer-Rao bounds (information/)."""
