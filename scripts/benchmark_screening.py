#!/usr/bin/env python
"""The consensus screening's share of a small solve (issue 27, "Speed"): the five real photographs of
Takahashi et al. (2012), one mirror, 10 x 7 corners.

    python scripts/benchmark_screening.py [--repeats 30] [--dataset PATH]

Prints the medians over ``--repeats`` in-process runs (after one warm-up) of ``calibrate()``'s wall
time and of its ``consensus`` stage (``Calibration.timings``: the per-image PnP, Sect. 4.1, which the
analytical solution then reuses, and the node-level least median of squares), their ratio against the
goal (<= 25 %), and the load average (the machine is shared).
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
    """Median wall time of ``calibrate`` and of its consensus stage (seconds), and their ratio."""
    from mirror_fg import calibrate, load_dataset

    dataset = load_dataset(dataset_path)
    calibrate(dataset)  # warm-up: imports, caches
    totals, screening, stages = [], [], []
    for _ in range(repeats):
        start = time.perf_counter()
        calibration = calibrate(dataset)
        totals.append(time.perf_counter() - start)
        screening.append(calibration.timings["consensus"])
        stages.append(calibration.timings.get("optimize", 0.0))
    total, screen = float(np.median(totals)), float(np.median(screening))
    return {"total_s": total, "screening_s": screen, "optimize_s": float(np.median(stages)),
            "fraction": screen / total}


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
    print(f"{args.dataset.parent.name}: screening {result['screening_s'] * 1e3:.1f} ms of a "
          f"{result['total_s'] * 1e3:.1f} ms solve ({100 * result['fraction']:.0f} %, goal <= "
          f"{100 * GOAL_FRACTION:.0f} %: {verdict}); optimizer {result['optimize_s'] * 1e3:.1f} ms; "
          f"load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
