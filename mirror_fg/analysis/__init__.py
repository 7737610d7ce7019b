"""Above the solver: planning a set-up (plan.py, plan_views.py), Monte Carlo studies (montecarlo.py and
its trial log), and whether a camera moved (verify.py, verify_priors.py, verify_study.py)."""
