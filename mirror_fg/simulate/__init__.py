"""Synthetic data (Sect. 7 of the paper): the tree (tree.py), views of any reflection order (views.py),
rigs (rig.py) and their ground truth (views_truth.py)."""
