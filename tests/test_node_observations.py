"""A node's observations for the consensus (solver/screen/placement_consensus.py): the ranking subset taken from
the node's gathered observations equals the observations gathered from those images alone, array for array."""
import numpy as np

from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.screen.placement_consensus import _NodeObservations
from mirror_fg.solver.start.peeling import spread_subset
from mirror_fg.solver.start.pnp import pnp_candidates_many


def test_subset_equals_the_images_gathered_alone():
    data, _ = simulate_base_case(num_images=120, mirror1_placements=3, num_fiducials=3, seed=0)
    problems = [(np.array([data.fiducials[n] for n in image.observations]),
                 np.array([data.normalized(image)[n] for n in image.observations])) for image in data.images]
    candidates = dict(zip((image.id for image in data.images), pnp_candidates_many(problems, data.num_mirrors)))
    assert max(len(c) for c in candidates.values()) > 1  # P3P's twins: several candidates per image
    images = data.images[:100]
    chosen = spread_subset(len(images), 64)
    subset = _NodeObservations(data, images, candidates).subset(chosen)
    alone = _NodeObservations(data, [images[k] for k in chosen], candidates)
    assert subset.num_images == alone.num_images == 64
    for name in ("A", "b", "owner", "index", "points", "observed", "counts", "first_candidate", "sigma"):
        assert np.array_equal(getattr(subset, name), getattr(alone, name)), name
