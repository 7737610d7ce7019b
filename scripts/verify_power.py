"""The detection power of ``mirror-fg verify`` on simulated data (mirror_fg/analysis/verify_study.py): how
often a camera moved by 3x the combined sigma of each pose component is called ``moved``, and how often an
unmoved one is (at most alpha + 2 %).

    PYTHONPATH=. python scripts/verify_power.py [--trials 200] [--seed 0] [--alpha 0.01] [--move-sigmas 3]
"""
from __future__ import annotations

import argparse
import time

from mirror_fg.analysis.verify_study import power_study


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--alpha", type=float, default=0.01)
    parser.add_argument("--move-sigmas", type=float, default=3.0)
    parser.add_argument("--stored-images", type=int, default=20)
    parser.add_argument("--new-images", type=int, default=3)
    args = parser.parse_args()
    began = time.perf_counter()
    f = power_study(args.trials, args.seed, args.alpha, args.move_sigmas, args.stored_images, args.new_images)
    print(f"{f.trials} trials, alpha {f.alpha}, {args.stored_images} stored images, {args.new_images} new placements "
          f"({time.perf_counter() - began:.0f} s)")
    print(f"no move:   'moved' {f.false_alarms}/{f.trials} = {100 * f.false_alarm_rate:.1f} % "
          f"(goal <= {100 * (f.alpha + 0.02):.0f} %), mean d2 {f.mean_d2_still:.2f} (dof 6); verdicts {f.verdicts_still}")
    print(f"{f.move_sigmas:g} sigma: 'moved' {f.detections}/{f.trials} = {100 * f.detection_rate:.1f} % (goal >= 95 %); "
          f"verdicts {f.verdicts_moved}")


if __name__ == "__main__":
    main()
