"""verify's p-value is the chi-square tail with the degrees of freedom the new images see (docs/formats.md,
"Has it moved?"): with one mirror placement (3 seen) a 6-dof tail would hide a move."""
from __future__ import annotations

import pytest
from scipy import stats
from test_verify import _scene

from mirror_fg.solver.verify import verify


@pytest.mark.parametrize("placements, dof", [(1, 3), (2, 5)])
def test_the_p_value_uses_the_degrees_of_freedom_seen(placements, dof):
    stored, new, _ = _scene(new_images=placements)
    answer = verify(stored, new).cameras["camera"]
    assert answer.dof == dof and answer.mahalanobis2 > 0
    assert answer.p_value == pytest.approx(stats.chi2.sf(answer.mahalanobis2, dof), rel=1e-9)


def test_the_statistic_is_the_move_s_mahalanobis_distance():
    """Linearised, ``d2 = 2 (cost_held - cost_free)`` is ``move^T C^-1 move`` with ``C = S + N^-1`` (the
    module docstring of solver/verify.py): the fits' cost difference against the move and its covariance."""
    import numpy as np

    stored, new, _ = _scene(new_images=3)
    answer = verify(stored, new).cameras["camera"]
    assert answer.dof == 6
    distance = float(answer.move @ np.linalg.solve(answer.covariance, answer.move))
    assert 0.8 < answer.mahalanobis2 / distance < 1.25, (answer.mahalanobis2, distance)
