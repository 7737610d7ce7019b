"""The registry's retry on a locked SQLite database: retried while SQLite says locked or busy, any other
database error raised at once (not retried for minutes as if it were a lock). The history's flagged changes
against hand-set calibrations: a move either way beyond the two calibrations' combined 3-sigma."""
from __future__ import annotations

import sqlite3

import pytest
from sqlalchemy.exc import OperationalError

import mirror_fg.registry.store as store
from mirror_fg.registry import Registry


def _failing(messages: list[str], calls: list[int]):
    """A unit of work that raises SQLite's OperationalError with each of ``messages`` in turn, then returns 7."""
    def work() -> int:
        calls.append(1)
        if len(calls) <= len(messages):
            raise OperationalError("INSERT INTO runs ...", {}, sqlite3.OperationalError(messages[len(calls) - 1]))
        return 7
    return work


@pytest.fixture
def registry(tmp_path, monkeypatch):
    monkeypatch.setattr(store._time, "sleep", lambda seconds: None)  # the back-off's pauses, not its logic
    with Registry(f"sqlite:///{tmp_path / 'r.db'}") as r:
        yield r


def test_a_locked_or_busy_database_is_retried_until_it_is_free(registry):
    calls: list[int] = []
    assert registry._retry(_failing(["database is locked", "database table is busy"], calls)) == 7
    assert len(calls) == 3


def test_another_database_error_is_raised_at_once(registry):
    calls: list[int] = []
    with pytest.raises(OperationalError, match="disk I/O error"):
        registry._retry(_failing(["disk I/O error"], calls))
    assert len(calls) == 1


def _calibration(run: int, t_mm, rotvec_deg, sigma_mm: float, sigma_deg: float):
    """A calibration record of camera ``cam`` (``T_base_cam``: position mm, rotation vector deg, via scipy)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from mirror_fg.registry.records import HistoryRecord

    q = Rotation.from_rotvec(np.radians(rotvec_deg)).as_quat()  # [x, y, z, w]
    return HistoryRecord("cam", None, tuple(np.asarray(t_mm, float) / 1000.0), tuple(q), (sigma_mm,) * 3,
                         (sigma_deg,) * 3, id=run, run_id=run, kind="calibration")


@pytest.mark.parametrize("shift_mm, flagged", [(-2.0, True), (2.0, True), (-1.2, False)])
def test_a_position_change_either_way_beyond_the_combined_3_sigma_is_flagged(shift_mm, flagged):
    """Two calibrations with 3-sigma 1 mm each: combined sqrt(2) = 1.41 mm; a move of 2 mm along -x or +x is a
    change, 1.2 mm is not."""
    from mirror_fg.registry.history import flag_changes

    before = _calibration(1, [100.0, 50.0, 300.0], [0.0, 0.0, 0.0], 1.0, 0.1)
    after = _calibration(2, [100.0 + shift_mm, 50.0, 300.0], [0.0, 0.0, 0.0], 1.0, 0.1)
    changes = flag_changes([before, after])
    assert bool(changes) == flagged
    if flagged:
        assert changes[0].position_mm[0] == pytest.approx(shift_mm, abs=1e-9)
        assert changes[0].position_sigma3_mm[0] == pytest.approx(2.0**0.5, rel=1e-12)


@pytest.mark.parametrize("turn_deg, flagged", [(0.15, False), (-0.15, False), (0.25, True), (-0.25, True)])
def test_a_rotation_change_is_judged_against_both_calibrations_3_sigma(turn_deg, flagged):
    """3-sigma 0.2 deg before and 0.05 deg after (a better calibration): combined hypot(0.2, 0.05) = 0.206 deg.
    A turn of 0.15 deg about z is within it (though beyond the newer one's 0.05 alone), 0.25 deg is not."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from mirror_fg.registry.history import flag_changes

    before = _calibration(1, [100.0, 50.0, 300.0], [1.0, 2.0, 3.0], 0.5, 0.2)
    after = _calibration(2, [100.0, 50.0, 300.0], [1.0, 2.0, 3.0], 0.5, 0.05)
    turned = Rotation.from_rotvec(np.radians([0.0, 0.0, turn_deg])) * Rotation.from_quat(after.q_xyzw)
    after.q_xyzw = tuple(turned.as_quat())
    changes = flag_changes([before, after])
    assert bool(changes) == flagged
    if flagged:
        np.testing.assert_allclose(changes[0].rotation_deg, [0.0, 0.0, turn_deg], atol=1e-9)
        assert changes[0].rotation_sigma3_deg[2] == pytest.approx(float(np.hypot(0.2, 0.05)), rel=1e-12)
