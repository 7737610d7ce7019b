#!/usr/bin/env python
"""The consensus screening's share of a small solve (the five real photographs of
Takahashi et al. (2012), one mirror, 10 x 7 corners.

    python scripts/benchmark_screening.py [--repeats 30] [--dataset PATH]

Prints the medians over ``--repeats`` in-process runs (after one warm-up) of ``calibrate()``'s wall
time and of two of its stages (``Calibration.timings``): ``consensus``, the screening (board sides and
the node-level least median of squares over placements), against the goal (<= 25 % of the solve), and
``pnp``, each image's PnP with its check (Sect. 4.1: the analytical solution starts from it, so it is
shared, not screening's own); the same in CPU time (``time.process_time``, which a busy machine inflates
less than wall time: the stages run again on their own for it); and the load average.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = REPO.parent / "shared" / "data" / "takahashi2012" / "dataset.json"
#: The screening may take at most this fraction of a small solve.
GOAL_FRACTION = 0.25


def measure(dataset_path: Path, repeats: int) -> dict[str, float]:
    """Medians (seconds) of ``calibrate``'s wall time and of its stages, the same in CPU time, and the ratios."""
    from mirror_fg import calibrate, load_dataset
    from mirror_fg.solver.screen import consensus

    check_images = getattr(consensus, "check_images", None)  # releases before it timed the PnP with the screening

    dataset = load_dataset(dataset_path)
    calibrate(dataset)  # warm-up: imports, caches
    runs: dict[str, list[float]] = {"total": [], "screening": [], "pnp": [], "optimize": [], "cpu_total": [],
                                    "cpu_screening": []}
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        calibration = calibrate(dataset)
        runs["total"].append(time.perf_counter() - start)
        runs["cpu_total"].append(time.process_time() - cpu_start)
        for stage, key in (("consensus", "screening"), ("pnp", "pnp"), ("optimize", "optimize")):
            runs[key].append(calibration.timings.get(stage, 0.0))
        checked = check_images(dataset) if check_images is not None else None
        cpu_start = time.process_time()
        consensus.screen(dataset, **({"checked": checked} if checked is not None else {}))
        runs["cpu_screening"].append(time.process_time() - cpu_start)
    result = {f"{key}_s": float(np.median(values)) for key, values in runs.items()}
    result["fraction"] = result["screening_s"] / result["total_s"]
    result["cpu_fraction"] = result["cpu_screening_s"] / result["cpu_total_s"]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    args = parser.parse_args(argv)
    if not args.dataset.exists():
        print(f"benchmark_screening: {args.dataset} not found", file=sys.stderr)
        return 2
    result = measure(args.dataset, args.repeats)
    verdict = "ok" if result["fraction"] <= GOAL_FRACTION else "above the goal"
    cpu_verdict = "ok" if result["cpu_fraction"] <= GOAL_FRACTION else "above the goal"
    print(f"{args.dataset.parent.name}: screening {result['screening_s'] * 1e3:.1f} ms of a "
          f"{result['total_s'] * 1e3:.1f} ms solve ({100 * result['fraction']:.0f} %, goal <= "
          f"{100 * GOAL_FRACTION:.0f} %: {verdict}); PnP {result['pnp_s'] * 1e3:.1f} ms; "
          f"optimizer {result['optimize_s'] * 1e3:.1f} ms; "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"CPU time: screening {result['cpu_screening_s'] * 1e3:.1f} ms of {result['cpu_total_s'] * 1e3:.1f} ms "
          f"({100 * result['cpu_fraction']:.0f} %: {cpu_verdict})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
