"""The robust kernel's default threshold, in a module free of numpy and GTSAM: the command line shows it
in its help without loading either (issue 27's start-up); ``batched.py`` and ``intrinsics.py`` use it."""

#: Default robust threshold in sigmas (as ``reflection.noise_model``).
ROBUST_K = 1.345
