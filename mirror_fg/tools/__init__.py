"""Around the solver: simulation (Sect. 7), Cramer-Rao bounds and planning, reports, Monte Carlo runs."""
