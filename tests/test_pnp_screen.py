"""The screen's PnP minima of many images (``pnp_screen.screen_minima_many``) keep what the full search
(``pnp.pnp_minima``) lets the check keep: on random and adversarial views (near and far, noisy and exact,
4-8 fiducials, nearly flat, nearly on a line, a rig's target, planar boards), seen directly and through
mirrors, an image whose minima differ from the full search's (fewer starts refined) has the same lowest
minimum, and every twin the full search keeps (``consensus.TWIN_COST_GAP``, ``PNP_POINT_SIGMAS``) is kept or
is that same lowest minimum reached by an LM that stopped early, and it keeps no other: polished by an
independent least squares (scipy), the kept minima are the same."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from mirror_fg.core.geometry import so3_exp_many
from mirror_fg.solver.screen.consensus import PNP_POINT_SIGMAS, TWIN_COST_GAP
from mirror_fg.solver.start import pnp_screen
from mirror_fg.solver.start.pnp import pnp_minima

FLIP = np.diag([1.0, -1.0, 1.0])
KINDS = ("random", "far", "flat", "line", "rig", "rig far", "planar")


def _view(rng: np.random.Generator, kind: str):
    """Fiducials (N, 3), their normalized observations (N, 2) and the screen's sigma, or None (a fiducial
    behind the camera)."""
    count = int(rng.integers(4, 9)) if kind in ("random", "planar") else int(rng.integers(4, 7))
    distance = rng.uniform(0.4, 3.0)
    points = rng.uniform(-0.15, 0.15, (count, 3))
    if kind == "far":  # a small target far away: weak perspective, twins
        points, distance = rng.uniform(-0.05, 0.05, (count, 3)), rng.uniform(2.0, 8.0)
    elif kind == "flat":
        points[:, 2] *= 10 ** rng.uniform(-4, -1)
    elif kind == "planar":
        points[:, 2] = 0.0
        distance = rng.uniform(0.4, 5.0)
    elif kind == "line":
        points = np.outer(rng.uniform(-0.15, 0.15, count), [1.0, 0.3, 0.2]) + rng.normal(
            scale=10 ** rng.uniform(-4, -2), size=(count, 3))
    elif kind.startswith("rig"):  # the three-camera rig's target (simulate/rig.py)
        points = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.05, 0.05, 0.075]])
        distance = rng.uniform(0.5, 2.0) if kind == "rig" else rng.uniform(2.0, 4.0)
    R = so3_exp_many(rng.normal(size=3) * rng.uniform(0.0, 1.5))[0]
    t = np.array([*rng.uniform(-0.2, 0.2, 2), distance])
    camera = points @ R.T + t
    if np.any(camera[:, 2] <= 0.05):
        return None
    noise = 1.0 / 800 if kind.startswith("rig") else float(rng.choice([0.0, 1e-4, 1e-3, 3e-3, 1e-2]))
    observed = camera[:, :2] / camera[:, 2:3] + rng.normal(scale=noise, size=camera[:, :2].shape)
    sigma = noise if kind.startswith("rig") else max(noise, float(rng.choice([1e-4, 1e-3])))
    return points, observed, np.array([sigma, sigma])


def _kept(minima, points, observed, sigma):
    """What the check keeps of the minima (``consensus._check_pnp``): the lowest, and the twins that fit
    every fiducial within PNP_POINT_SIGMAS and cost less than TWIN_COST_GAP more (only the lowest where it
    does not fit)."""
    costs, fits = [], []
    for A, b in minima:
        camera = points @ A.T + b
        errors = np.linalg.norm((camera[:, :2] / camera[:, 2:3] - observed) / sigma, axis=1)
        errors = np.where(camera[:, 2] > 0, errors, np.inf)
        costs.append(float(np.sum(errors**2)))
        fits.append(bool(np.all(errors <= PNP_POINT_SIGMAS)))
    if not minima or not fits[0]:
        return minima[:1]
    return minima[:1] + [m for m, c, f in zip(minima[1:], costs[1:], fits[1:]) if f and c - costs[0] < TWIN_COST_GAP]


def _polished(points, observed, A, b, flip):
    """The least-squares minimum (scipy, to machine precision) reached from the map ``(A, b)`` (eq. 10)."""
    R, t = (FLIP @ A, FLIP @ b) if flip else (A, b)
    rigid = observed * ([1.0, -1.0] if flip else 1.0)

    def residuals(x):
        camera = points @ (so3_exp_many(x[:3])[0] @ R).T + t + x[3:]
        return (camera[:, :2] / camera[:, 2:3] - rigid).ravel()

    x = least_squares(residuals, np.zeros(6), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    return so3_exp_many(x[:3])[0] @ R, t + x[3:]


def _same(first, second, tolerance):
    (R1, t1), (R2, t2) = first, second
    return np.abs(R1 - R2).max() <= tolerance and np.linalg.norm(t1 - t2) <= tolerance * np.linalg.norm(t1)


def _compare(rng: np.random.Generator, cases: int) -> dict[str, int]:
    """Views of every kind through screen_minima_many and the full search: how many got other minima than the
    full search's (``alone``: fewer starts refined), and how many of those differ in a minimum the check
    keeps (``dropped``)."""
    counts = dict.fromkeys(("views", "alone", "dropped"), 0)
    per_kind = {kind: [0, 0] for kind in KINDS}
    for kind in KINDS:
        views = []
        while len(views) < cases:
            view = _view(rng, kind)
            if view is not None:
                views.append((*view, int(rng.integers(0, 3))))
        problems = [(points, observed * ([1.0, -1.0] if parity % 2 else 1.0)) for points, observed, _, parity in views]
        for (points, _, sigma, parity), problem in zip(views, problems):
            found = pnp_screen.screen_minima_many([problem], [parity], sigma, TWIN_COST_GAP)[0]
            full = pnp_minima(problem[0], problem[1], parity)
            counts["views"] += 1
            per_kind[kind][0] += 1
            if len(found) == len(full) and all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
                                               for a, b in zip(found, full)):
                continue  # the full search's own answer
            counts["alone"] += 1
            per_kind[kind][1] += 1
            flip = parity % 2 == 1
            kept_full = [_polished(points, problem[1], *m, flip) for m in _kept(full, points, problem[1], sigma)]
            kept_found = [_polished(points, problem[1], *m, flip) for m in _kept(found, points, problem[1], sigma)]
            ok = _same(kept_found[0], kept_full[0], 1e-6)  # the same lowest minimum
            for twin in kept_full[1:]:  # each twin the full search keeps: the lowest stopped early, or kept
                ok &= any(_same(twin, kept, 1e-6) for kept in kept_found)
            for twin in kept_found[1:]:  # and nothing else
                ok &= any(_same(twin, kept, 1e-6) for kept in kept_full)
            counts["dropped"] += not ok
    counts["rig alone"] = per_kind["rig"][1]
    counts["rig views"] = per_kind["rig"][0]
    return counts


def test_fewer_refinements_drop_nothing_the_check_keeps() -> None:
    counts = _compare(np.random.default_rng(0), 40)
    assert counts["dropped"] == 0
    assert counts["alone"] >= 0.15 * counts["views"]
    assert counts["rig alone"] >= 0.7 * counts["rig views"]  # the rig's clear views: one LM each


@pytest.mark.slow
def test_fewer_refinements_drop_nothing_the_check_keeps_thousands() -> None:
    counts = _compare(np.random.default_rng(1), 600)
    assert counts["dropped"] == 0


def test_a_reckless_rule_is_caught(monkeypatch) -> None:
    """The comparison can fail: vouching for every start (no basin test, no bound on what a P3P start
    could reach, any ellipsoid) drops minima the full search keeps."""
    monkeypatch.setattr(pnp_screen, "CONTRACTION", np.inf)
    monkeypatch.setattr(pnp_screen, "ELLIPSOID_REACH", np.inf)
    monkeypatch.setattr(pnp_screen, "MISS_MARGIN", -np.inf)
    assert _compare(np.random.default_rng(0), 40)["dropped"] > 0


def test_many_images_at_once_as_one_at_a_time() -> None:
    """Judged together (fiducial counts mixed, parities mixed) each image gets what it gets alone."""
    rng = np.random.default_rng(5)
    views = [view for view in (_view(rng, kind) for kind in KINDS * 6) if view is not None]
    parities = [int(rng.integers(0, 3)) for _ in views]
    problems = [(points, observed) for points, observed, _, in views]
    sigma = views[0][2]
    together = pnp_screen.screen_minima_many(problems, parities, sigma, TWIN_COST_GAP)
    for problem, parity, found in zip(problems, parities, together):
        alone = pnp_screen.screen_minima_many([problem], [parity], sigma, TWIN_COST_GAP)[0]
        assert len(found) == len(alone)
        assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(found, alone))


def test_first_of_each_of_every_group_at_once_as_group_by_group() -> None:
    """The starts of one basin merged for all images at once keep what the search keeps image by image
    (``pnp.first_of_each``): groups of 1-12 poses, some repeated within the tolerance, some just outside."""
    from mirror_fg.solver.start.pnp import SAME_BASIN, first_of_each, first_of_each_grouped

    rng = np.random.default_rng(7)
    R_parts, t_parts, owner = [], [], []
    for group in range(300):
        size = int(rng.integers(1, 13))
        R = so3_exp_many(rng.normal(scale=1.0, size=(size, 3)))
        t = rng.normal(size=(size, 3)) + np.array([0.0, 0.0, 3.0])
        for k in range(1, size):  # a near copy of an earlier pose, within or just beyond the tolerance
            if rng.random() < 0.5:
                j = int(rng.integers(0, k))
                factor = rng.choice([0.3, 0.9, 1.5])
                R[k] = so3_exp_many((factor * SAME_BASIN * rng.uniform(-1, 1, size=(1, 3))))[0] @ R[j]
                t[k] = t[j] * (1.0 + factor * SAME_BASIN * rng.uniform(-0.5, 0.5))
        R_parts.append(R)
        t_parts.append(t)
        owner += [group] * size
    R_all, t_all, owner_array = np.concatenate(R_parts), np.concatenate(t_parts), np.array(owner)
    expected, at = [], 0
    for R, t in zip(R_parts, t_parts):
        expected += [at + k for k in first_of_each(R, t, SAME_BASIN)]
        at += len(R)
    assert len(expected) < len(owner)  # some merged: the comparison means something
    assert first_of_each_grouped(R_all, t_all, owner_array, SAME_BASIN).tolist() == expected
