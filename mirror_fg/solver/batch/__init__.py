"""The problems ``calibrate()`` solves in one batch: the paper's tree, the general views, the joint solve
with intrinsics, the arm, and several screens."""
