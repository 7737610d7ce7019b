"""The analytical start: PnP per image (eqs. 5-12), the paper's peeling of the tree (eqs. 13-18), the
propagation for any views, the reconstruction of unknown points (eqs. 19-20) and the arm's start."""
