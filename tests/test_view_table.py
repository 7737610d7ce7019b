"""The view model's views as blocks of one shape (factors/view_table.py) against the per-image factors: the
stacks, the groups of one shape and the keys that ``view_stack`` computes from the per-image ``ViewFactor`` s
(``stacks_by_placements``, ``groups_by_shape``, ``collected_keys``), the placements a stack alone sees against
their definition (a greedy pass over the views), on the paper's tree (with reconstruction points), a
kaleidoscope with repeated placements, rigs whose cameras see each other's placements and direct views; the
stacks' merging against a set per view and the distinct rows against numpy's, on random sets."""
from __future__ import annotations

import numpy as np
import pytest

import views_scenes as scenes
from mirror_fg.factors.view_stack import collected_keys, groups_by_shape, stacks_by_placements
from mirror_fg.factors.view_table import ViewTable, merged_sets, unique_rows
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.model.views import ViewProblem


def _tree():
    return simulate_base_case(num_images=40, num_points=2, mirror1_placements=3, pixel_sigma=1.0, mirror_distance=0.5,
                              tilt_deg=30.0, seed=0, num_mirrors=2, num_fiducials=3)[0]


def _kaleidoscope():
    return dataset_from_dict(scenes.kaleidoscope_three_mirrors_one_point(0)[0])


def _rig():
    return dataset_from_dict(simulate_rig_mixed(3, own=[4, 4, 4], shared=4, seed=2)[0])


def _rig_handheld():
    return dataset_from_dict(scenes.rig_two_cameras(0)[0])


def _direct():
    return dataset_from_dict(scenes.mixed_one_mirror_gives_pose(0)[0])


SCENES = pytest.mark.parametrize("make", [_tree, _kaleidoscope, _rig, _rig_handheld, _direct],
                                 ids=["tree", "kaleidoscope", "rig", "rig-handheld", "direct"])


def _private_reference(view_factors, stacks, keep) -> list:
    """The placements to eliminate by their definition: seen by one stack's views only, not in ``keep``, last
    in every view's reflections and owned by that view's camera; greedily, those with the fewest views first,
    at most one per view."""
    stack_of = {i: s for s, members in enumerate(stacks) for i in members}
    views_of: dict = {}
    bad = set(keep)
    for i, f in enumerate(view_factors):
        for p in f.mirror_keys:
            views_of.setdefault(p, []).append(i)
            if p != f.reflections[-1] or f.owners[p] != f.camera:
                bad.add(p)
    for p, views in views_of.items():
        if len({stack_of[i] for i in views}) > 1:
            bad.add(p)
    taken: set = set()
    chosen = []
    for p in sorted((p for p in views_of if p not in bad), key=lambda p: (len(views_of[p]), p)):
        if not taken.intersection(views_of[p]):
            chosen.append(p)
            taken.update(views_of[p])
    return sorted(chosen)


@SCENES
def test_table_as_the_per_image_factors(make):
    problem = ViewProblem(make())
    factors = problem.factors
    for table in (problem.table, ViewTable.of_factors(factors)):
        assert table.count == len(factors)
        for limit in (1, 2, 3, 16, 256):
            stacks = table.stacks(limit)
            assert [m.tolist() for m in stacks] == stacks_by_placements(factors, limit)
            for keep in (set(), set(problem.placements[:2])):
                assert table.private_placements(stacks, keep) == _private_reference(factors, stacks, keep)
        assert [members.tolist() for _, members, _ in table.groups()] == groups_by_shape(factors)
        mask = np.arange(len(table.placements)) % 2 == 0  # any placements "eliminated"
        chosen = {p for p, m in zip(table.placements, mask) if m}
        assert ([members.tolist() for _, members, _ in table.groups(mask)]
                == groups_by_shape(factors, lambda f, chosen=chosen: tuple(p in chosen for p in f.mirror_keys)))
        fixed, poses, planes = collected_keys(factors)
        fixed_t, poses_t, planes_t = table.collected_keys()
        assert list(fixed_t) == list(fixed) and poses_t == poses and list(planes_t.items()) == list(planes.items())
        for first, members, parts in table.groups():  # each group's arrays: those of its views' factors
            group = table.group_of(first, parts)
            views = [factors[i] for i in members]
            assert np.array_equal(group.observed, np.array([f.observed for f in views]))
            assert np.array_equal(group.sigmas, np.array([f.sigmas for f in views]))
            assert np.array_equal(group.base, np.array([f.base_points for f in views]), equal_nan=True)
            assert np.array_equal(group.landmarks, np.array([f.landmark_keys for f in views]).reshape(len(views), -1))
            assert [[table.placements[u] for u in row] for row in group.placement_ids.tolist()] == \
                [list(f.mirror_keys) for f in views]


def test_merging_as_a_set_per_view():
    def reference(sets, limit):
        out, merged, s = [], set(), -1
        for row in sets.tolist():
            union = merged | {p for p in row if p >= 0}
            if s >= 0 and len(union) <= limit:
                merged = union
            else:
                s, merged = s + 1, {p for p in row if p >= 0}
            out.append(s)
        return out

    rng = np.random.default_rng(1)
    for _ in range(500):
        sets = rng.integers(-1, int(rng.integers(1, 30)), (int(rng.integers(1, 80)), int(rng.integers(1, 4))))
        limit = int(rng.integers(1, 8))
        assert merged_sets(sets, limit).tolist() == reference(sets, limit)


def test_unique_rows_as_numpy():
    rng = np.random.default_rng(2)
    for _ in range(200):
        rows = rng.integers(-1, 4, (int(rng.integers(1, 40)), int(rng.integers(0, 4))))
        _, first, which = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        mine_first, mine_which = unique_rows(rows)
        assert mine_first.tolist() == first.tolist() and mine_which.tolist() == which.reshape(-1).tolist()
