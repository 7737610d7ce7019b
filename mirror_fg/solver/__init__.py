"""The solver: analytical solution (Sects. 4-5), factor graph, Levenberg-Marquardt, marginals, iSAM2."""
