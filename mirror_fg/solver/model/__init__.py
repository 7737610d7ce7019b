"""The measurement model and its solve: the factor graph's keys and layout (graph.py for the paper's tree,
views.py for any view, robot_views.py for an arm), Levenberg-Marquardt (lm.py), the marginals, the
residuals and the rig chain."""
