#!/usr/bin/env python
"""LM iterations and success rate from the analytical initial guess vs a naive one (paper's Sect. 7).

Per run (simulator base case, seed = run index): the global optimum is the MLE started from the truth;
the MLE is then computed by ``calibrate()`` from its analytical solution
(``mirror_fg.initial_estimate``: the closed form with each mirror placement's P3P hypotheses
refined on its own images; when LM ends at an implausible cost it restarts from the runner-up
hypotheses, counted as ``restarts``), by LM from the bare closed form of Sects. 4-5
(``solve_analytic``), and by LM from a naive guess (identity rotation,
``t_cam_base = 0``, every placement of mirror l facing the camera at ``--naive-distance`` m along its
nominal axis - mirror Nv at +z in front, mirror Nv-1 at -z behind, ... - and every reconstruction
point at the fiducials' centroid). A start *succeeds* when LM stops (before its iteration limit) at the
global optimum: pose within 1e-4 rad / 1e-4 m of it (LM's stopping rule usually leaves about 1e-6
between two starts that end at the same optimum, but 1e-5 m in a flat valley - seed 28 of the base
case, cost gap 1.5e-11 relative; other minima are centimetres and degrees away) and a cost no more
than 1e-6 relative above it.
A run whose analytical solution cannot be formed (degenerate mirror motion) is *singular*; the paper
counts success over non-singular runs. The paper reports about 4 vs 18 iterations and 100 % success
from its analytical guess.

Usage: ``python scripts/convergence.py --runs 100 --jobs 2 --out out/convergence``; writes
``runs.jsonl`` (resumable, ``analysis/trial_log.py``) and ``summary.json`` and prints the table.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from mirror_fg import calibrate, initial_estimate
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.transform import rotation_angle
from mirror_fg.data import Dataset
from mirror_fg.solver.start.analytic import solve_analytic
from mirror_fg.solver.model.graph import Estimate
from mirror_fg.analysis.montecarlo import run_script, run_trials
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.analysis.trial_log import TrialLog

#: A start reached the global optimum when within these of the MLE started from the truth.
POSE_TOL_RAD = 1e-4
POSE_TOL_M = 1e-4
COST_REL_TOL = 1e-6


#: Initial values that know nothing about the scene (see the module docstring).
NaiveGuess = Estimate


def naive_guess(dataset: Dataset, distance_m: float = 0.5) -> NaiveGuess:
    """Identity rotation, zero translation, mirrors facing the camera, points at the fiducials' centroid."""
    Nv = dataset.num_mirrors
    centroid = np.mean(np.array(list(dataset.fiducials.values())), axis=0)
    # Mirror Nv faces the camera from the front (+z), the one before it from behind, alternating.
    mirrors = {(l, m): np.array([0.0, 0.0, distance_m if (Nv - l) % 2 == 0 else -distance_m])
               for l, m in dataset.configurations}
    points = {name: centroid.copy() for name in dataset.reconstruction_point_names}
    return NaiveGuess(np.eye(3), np.zeros(3), mirrors, points)


def _outcome(cal, optimum) -> dict:
    """How far one LM start ended from the global optimum."""
    return {
        "iterations": cal.iterations,
        "rotation_off_rad": rotation_angle(cal.R_cam_base, optimum.R_cam_base),
        "translation_off_m": float(np.linalg.norm(cal.t_cam_base - optimum.t_cam_base)),
        "cost_gap_rel": (cal.final_error - optimum.final_error) / max(optimum.final_error, 1e-12),
        "final_error": cal.final_error,
        "initial_error": cal.initial_error,
    }


def succeeded(outcome: dict, max_iterations: int = 100) -> bool:
    """Whether an LM start stopped, before its iteration limit, at the global optimum (tolerances above)."""
    if "rotation_off_rad" not in outcome:  # the start failed outright
        return False
    return bool(outcome["iterations"] < max_iterations and outcome["rotation_off_rad"] < POSE_TOL_RAD
                and outcome["translation_off_m"] < POSE_TOL_M and outcome["cost_gap_rel"] < COST_REL_TOL)


def run_trial(seed: int, sigma_px: float = 1.0, distance_m: float = 0.5, num_images: int = 200,
              num_points: int = 0, naive_distance_m: float = 0.5, max_iterations: int = 100) -> dict:
    """The three LM starts of one simulated base case (see the module docstring)."""
    record: dict = {"seed": seed, "sigma_px": sigma_px, "distance_m": distance_m, "num_images": num_images,
                    "num_points": num_points, "max_iterations": max_iterations}
    start = time.perf_counter()
    dataset, truth = simulate_base_case(num_images=num_images, num_points=num_points, pixel_sigma=sigma_px,
                                        mirror_distance=distance_m, seed=seed)
    optimum = calibrate(dataset, initial=truth, compute_covariance=False, max_iterations=max_iterations)
    record["optimum"] = {"iterations": optimum.iterations, "final_error": optimum.final_error,
                         "converged": optimum.converged}
    try:
        initial_estimate(dataset)  # raises when the analytical solution cannot be formed: a singular run
    except (SolveError, DatasetError) as error:
        record["analytic"] = {"singular": True, "message": str(error)}
    else:
        try:
            cal = calibrate(dataset, compute_covariance=False, max_iterations=max_iterations)
        except SolveError as error:  # LM met an indeterminant system: a failure
            record["analytic"] = {"singular": False, "iterations": max_iterations, "error": str(error)}
        else:
            record["analytic"] = {"singular": False, "restarts": cal.restarts, **_outcome(cal, optimum)}
    try:
        closed_form = solve_analytic(dataset)
    except (SolveError, DatasetError) as error:
        record["closed_form"] = {"singular": True, "message": str(error)}
    else:
        try:
            cal = calibrate(dataset, initial=closed_form, compute_covariance=False, max_iterations=max_iterations)
        except SolveError as error:
            record["closed_form"] = {"singular": False, "iterations": max_iterations, "error": str(error)}
        else:
            record["closed_form"] = {"singular": False, **_outcome(cal, optimum)}
    try:
        cal = calibrate(dataset, initial=naive_guess(dataset, naive_distance_m), compute_covariance=False,
                        max_iterations=max_iterations)
    except (SolveError, RuntimeError) as error:  # an indeterminant system from a wild start is a failure
        record["naive"] = {"iterations": max_iterations, "error": str(error)}
    else:
        record["naive"] = _outcome(cal, optimum)
    record["seconds"] = time.perf_counter() - start
    return record


def summarize(records: list[dict]) -> dict:
    """Success rates and iteration counts of both starts (analytical: over non-singular runs)."""
    def ok(r: dict, start: str) -> bool:
        return succeeded(r[start], r.get("max_iterations", 100))

    nonsingular = [r for r in records if not r["analytic"]["singular"]]
    analytic_it = [r["analytic"]["iterations"] for r in nonsingular]
    closed = [r for r in nonsingular if "closed_form" in r and not r["closed_form"]["singular"]]
    closed_it = [r["closed_form"]["iterations"] for r in closed]
    naive_it = [r["naive"]["iterations"] for r in records]
    naive_ok_it = [r["naive"]["iterations"] for r in records if ok(r, "naive")]
    return {
        "runs": len(records),
        "singular": len(records) - len(nonsingular),
        "optimum_iterations_median": float(np.median([r["optimum"]["iterations"] for r in records])),
        "analytic_success": sum(ok(r, "analytic") for r in nonsingular),
        "analytic_success_rate": float(np.mean([ok(r, "analytic") for r in nonsingular])) if nonsingular else None,
        "analytic_iterations_median": float(np.median(analytic_it)) if analytic_it else None,
        "analytic_iterations_mean": float(np.mean(analytic_it)) if analytic_it else None,
        "analytic_iterations_max": int(np.max(analytic_it)) if analytic_it else None,
        "analytic_restarted": sum(r["analytic"].get("restarts", 0) > 0 for r in nonsingular),
        "closed_form_runs": len(closed),
        "closed_form_success": sum(ok(r, "closed_form") for r in closed),
        "closed_form_iterations_median": float(np.median(closed_it)) if closed_it else None,
        "failed_closed_form_seeds": [r["seed"] for r in closed if not ok(r, "closed_form")],
        "naive_success": sum(ok(r, "naive") for r in records),
        "naive_success_rate": float(np.mean([ok(r, "naive") for r in records])),
        "naive_success_nonsingular_rate": float(np.mean([ok(r, "naive") for r in nonsingular])) if nonsingular else None,
        "naive_iterations_median": float(np.median(naive_it)),
        "naive_iterations_mean": float(np.mean(naive_it)),
        "naive_iterations_median_successful": float(np.median(naive_ok_it)) if naive_ok_it else None,
        "failed_analytic_seeds": [r["seed"] for r in nonsingular if not ok(r, "analytic")],
        "singular_seeds": [r["seed"] for r in records if r["analytic"]["singular"]],
    }


def format_summary(s: dict) -> str:
    lines = [
        f"runs: {s['runs']} ({s['singular']} singular: analytical solution impossible)",
        f"global optimum (MLE from the truth): median {s['optimum_iterations_median']:.0f} LM iterations",
        f"from the analytical guess: success {s['analytic_success']}/{s['runs'] - s['singular']} non-singular runs "
        f"({100 * (s['analytic_success_rate'] or 0):.1f} %), LM iterations median {s['analytic_iterations_median']}, "
        f"mean {s['analytic_iterations_mean']:.2f}, max {s['analytic_iterations_max']}; "
        f"{s['analytic_restarted']} run(s) needed a restart from a runner-up hypothesis"
        if s["analytic_iterations_median"] is not None else "from the analytical guess: no non-singular run",
        f"from the bare closed form (Sects. 4-5, no refinement): success {s['closed_form_success']}/"
        f"{s['closed_form_runs']}, LM iterations median {s['closed_form_iterations_median']}"
        + (f", failures at seeds {s['failed_closed_form_seeds']}" if s["failed_closed_form_seeds"] else ""),
        f"from the naive guess: success {s['naive_success']}/{s['runs']} ({100 * s['naive_success_rate']:.1f} %), "
        f"LM iterations median {s['naive_iterations_median']:.0f} (mean {s['naive_iterations_mean']:.1f}; "
        f"median over its successful runs {s['naive_iterations_median_successful']})",
        "paper (Sect. 7): typically 4 iterations from the analytical guess (100 % success on non-singular "
        "configurations) vs 18 from a naive one",
    ]
    if s["failed_analytic_seeds"]:
        lines.append(f"analytical-guess failures at seeds {s['failed_analytic_seeds']}")
    return "\n".join(lines)


#: The fields that name one run in the log (a run is kept once per key).
TRIAL_KEY = ("seed", "sigma_px", "distance_m", "num_images", "num_points")


def run_all(runs: int, jobs: int, trial_kwargs: dict, log_path: Path | None, time_budget_s: float | None,
            progress: bool = True, fresh: bool = False) -> list[dict]:
    """Every run (resumed from and appended to ``log_path``, a ``TrialLog`` locked while this runs; ``fresh``:
    emptied first), in parallel over ``jobs`` processes."""
    setup = {k: v for k, v in trial_kwargs.items() if k in TRIAL_KEY}
    with TrialLog(log_path, TRIAL_KEY, fresh=fresh) as log:
        records = [r for r in log.records if all(r.get(k) == v for k, v in setup.items()) and r["seed"] < runs]
        have = {r["seed"] for r in records}
        todo = [seed for seed in range(runs) if seed not in have]
        run_trials(run_trial, [dict(seed=seed, **trial_kwargs) for seed in todo], records, total=runs,
                   log=log, desc="convergence runs", progress=progress, jobs=jobs, time_budget_s=time_budget_s)
    return sorted(records, key=lambda r: r["seed"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100, help="Monte Carlo runs (default 100)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: all cores)")
    parser.add_argument("--sigma", type=float, default=1.0, help="pixel noise, pixels (default 1)")
    parser.add_argument("--distance", type=float, default=0.5, help="mirror distance, metres (default 0.5)")
    parser.add_argument("--images", type=int, default=200, help="images per run (default 200)")
    parser.add_argument("--points", type=int, default=0,
                        help="reconstruction points per run (default 0: the paper's base case for this claim)")
    parser.add_argument("--naive-distance", type=float, default=0.5, help="naive guess's mirror distance, m")
    parser.add_argument("--max-iterations", type=int, default=100, help="LM iteration limit (default 100)")
    parser.add_argument("--out", type=Path, default=Path("out/convergence"), help="output directory")
    parser.add_argument("--fresh", action="store_true", help="ignore runs already in OUT/runs.jsonl")
    parser.add_argument("--time-budget", type=float, default=None, metavar="MIN",
                        help="stop starting new runs after MIN minutes")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    log_path = args.out / "runs.jsonl"
    trial_kwargs = dict(sigma_px=args.sigma, distance_m=args.distance, num_images=args.images,
                        num_points=args.points, naive_distance_m=args.naive_distance,
                        max_iterations=args.max_iterations)
    records = run_all(args.runs, args.jobs, trial_kwargs, log_path,
                      None if args.time_budget is None else 60.0 * args.time_budget, not args.no_progress,
                      fresh=args.fresh)
    summary = summarize(records)
    summary["setup"] = trial_kwargs
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(format_summary(summary))
    print(f"wrote {args.out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
