#!/usr/bin/env python
"""Reproduce the paper's Fig. 4 (Hesch et al., ECCV 2010, Sect. 7) on the simulator's base case, and more.

Base case: two mirrors, the 20 cm right triangle of 3 fiducials, 200 images, 60 reconstruction points
within 10 cm of the fiducials. Sweeps: (a) pixel sigma at 0.5 m mirror distance, (b) mirror distance at
1 px. Per point of a sweep, ``--runs`` Monte Carlo runs (seed = run index; in sweep (a) a run keeps its
mirror placements and only the noise scale changes). Each run: the analytical solution and the MLE
(``mirror_fg.calibrate``), its reported covariance, and the Cramér-Rao bound (inverse Fisher
information at the truth, ``mirror_fg.solver.information.crb``). "Analytical" is ``calibrate()``'s start
(``mirror_fg.initial_estimate``: the closed form with each mirror placement's P3P hypotheses refined on its
own images); the bare closed form of Sects. 4-5 (``solve_analytic``, the paper's method) is reported
beside it as "closed form".

Reported per point (least-accurate-axis convention of the paper: RMS over runs per axis, then the
largest of the three axes; rotation about the camera axes in degrees, position ``t_cam_base`` in m):
analytical RMS error, MLE RMS error, reported MLE 1-sigma (quadratic mean over runs), Cramér-Rao
1-sigma (quadratic mean over runs); (c), (d) the same for the least-accurately reconstructed point of
each run, chosen as the point with the largest Cramér-Rao bound (a property of the geometry, so the
selection does not depend on the noise; the realized worst point is in the CSV too).
Checks: efficiency ``MLE RMS / CRB 1-sigma`` per axis, also against the first-order efficient estimator
on the same noise (no sampling error), consistency ``reported 1-sigma / MLE RMS`` and the pose NEES.

Sampling error: the plain RMS over 100 runs estimates a standard deviation to about 7 % per axis, more
when the runs' geometries (and so their sigmas) differ. The first-order estimator ``x_true + I^-1 J^T
Sigma^-1 (z - h(x_true))`` of each run has the Cramér-Rao covariance exactly, so it serves as a control
variate: ``MSE_cv = mean(CRB variance) + mean(mle_error^2 - first_order_error^2)`` estimates the MLE's
mean squared error without bias and with the noise of the estimate mostly cancelled (``*_cv`` columns).

Writes ``runs.jsonl`` (one line per run; a re-run resumes from it: ``analysis/trial_log.py`` says what a killed
run, a full disk or a second run on the same ``--out`` leave), ``fig4.csv`` and ``fig4.png`` in ``--out``. Usage: ``python scripts/reproduce_fig4.py --runs 100 --jobs 2 --out out/fig4`` (about 2 h on a 2-core
machine: it says so when it starts; ``--time-budget MIN`` bounds it).

Over 500 lines: the whole experiment (trials, summary, CSV, figure) as one runnable, resumable script.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS thread per worker process

import argparse
import csv
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from mirror_fg import calibrate
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.solver.start.analytic import solve_analytic
from mirror_fg.solver.information.crb import cramer_rao_bound, nees, nees_band, pose_error
from mirror_fg.analysis.montecarlo import run_script, run_trials
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.analysis.trial_log import TrialLog

SIGMAS_PX = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
DISTANCES_M = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5)
BASE_SIGMA_PX = 1.0
BASE_DISTANCE_M = 0.5
AXES = ("x", "y", "z")
#: An MLE error beyond this many Cramér-Rao sigmas on some pose axis (probability ~1e-9 for an MLE at
#: the global optimum) marks a run whose LM stopped in another local minimum.
LOCAL_MINIMUM_SIGMAS = 6.0


# --- one Monte Carlo run ----------------------------------------------------------------------------


def run_trial(sigma_px: float, distance_m: float, seed: int, num_images: int = 200, num_points: int = 60) -> dict:
    """One base-case simulation, its analytical solution, MLE and Cramér-Rao bound, as plain data.

    Errors are docs/formats.md's "true minus estimate": pose ``[dtheta (rad), dt (m)]`` about/along the camera axes,
    points in the base frame (m). A run whose analytical solution or MLE cannot be formed (degenerate
    geometry) has ``status`` ``"singular"`` and the message.
    """
    record: dict = {
        "sigma_px": sigma_px, "distance_m": distance_m, "seed": seed,
        "num_images": num_images, "num_points": num_points,
    }
    start = time.perf_counter()
    dataset, truth = simulate_base_case(
        num_images=num_images, num_points=num_points, pixel_sigma=sigma_px, mirror_distance=distance_m, seed=seed
    )
    bound = cramer_rao_bound(dataset, truth, with_score=True)
    try:
        closed_form = solve_analytic(dataset)
        cal = calibrate(dataset)
    except (SolveError, DatasetError) as error:
        record.update(status="singular", message=str(error), seconds=time.perf_counter() - start)
        return record
    first_order_pose, first_order_points = bound.first_order_errors()
    R, t = truth.R_cam_base, truth.t_cam_base
    record.update(
        status="ok",
        iterations=cal.iterations,
        converged=cal.converged,
        initial_error=cal.initial_error,
        final_error=cal.final_error,
        num_measurements=bound.linearization.num_measurements,
        num_unknowns=bound.linearization.index.size,
        analytic_pose=pose_error(R, t, cal.analytic.R_cam_base, cal.analytic.t_cam_base).tolist(),
        closed_form_pose=pose_error(R, t, closed_form.R_cam_base, closed_form.t_cam_base).tolist(),
        mle_pose=pose_error(R, t, cal.R_cam_base, cal.t_cam_base).tolist(),
        first_order_pose=first_order_pose.tolist(),
        reported_cov=cal.covariance.tolist(),
        crb_cov=bound.pose_covariance.tolist(),
    )
    if truth.points:
        names = sorted(truth.points)
        # Least-accurately reconstructed point: largest worst-axis Cramér-Rao sigma (geometry only).
        worst = max(names, key=lambda n: float(np.max(np.diag(bound.point_covariances[n]))))
        analytic_err = {n: truth.points[n] - cal.analytic.points[n] for n in names}
        mle_err = {n: truth.points[n] - cal.points[n] for n in names}
        record.update(
            worst_point=worst,
            analytic_point=analytic_err[worst].tolist(),
            closed_form_point=(truth.points[worst] - closed_form.points[worst]).tolist(),
            mle_point=mle_err[worst].tolist(),
            first_order_point=first_order_points[worst].tolist(),
            crb_point_var=np.diag(bound.point_covariances[worst]).tolist(),
            reported_point_var=np.diag(cal.point_covariances[worst]).tolist(),
            analytic_point_max_norm=max(float(np.linalg.norm(e)) for e in analytic_err.values()),
            mle_point_max_norm=max(float(np.linalg.norm(e)) for e in mle_err.values()),
        )
    record["timings"] = {k: round(v, 3) for k, v in cal.timings.items()}
    record["seconds"] = time.perf_counter() - start
    return record


# --- statistics -------------------------------------------------------------------------------------


def _rms(values: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.square(values), axis=0))


def is_local_minimum(record: dict) -> bool:
    """Whether the run's MLE is more than LOCAL_MINIMUM_SIGMAS Cramér-Rao sigmas off the truth on some axis."""
    sigma = np.sqrt(np.diag(np.array(record["crb_cov"])))
    return bool(np.max(np.abs(np.array(record["mle_pose"]) / sigma)) > LOCAL_MINIMUM_SIGMAS)


def summarize(records: list[dict]) -> dict:
    """Statistics of the runs of one (sigma, distance) point; see the module docstring for the conventions.

    Per-axis arrays are ``[rot x, rot y, rot z, pos x, pos y, pos z]`` (radians, metres) for the pose and
    ``[x, y, z]`` (metres, base frame) for the point. Accuracy (``analytic_rms``, ``mle_rms``, points) is
    over every non-singular run, as in the paper's figure; the efficiency, consistency and NEES of the
    MLE are over the runs whose LM reached the global optimum (see :func:`is_local_minimum`), whose
    count is ``runs_global``.
    """
    ok = [r for r in records if r["status"] == "ok"]
    out: dict = {"runs_ok": len(ok), "runs_singular": len(records) - len(ok)}
    if not ok:
        return out
    good = [r for r in ok if not is_local_minimum(r)]
    out["runs_global"] = len(good)
    out["runs_local_minimum"] = len(ok) - len(good)
    out["local_minimum_seeds"] = [r["seed"] for r in ok if is_local_minimum(r)]

    def stack(key: str, runs: list[dict]) -> np.ndarray:
        return np.array([r[key] for r in runs])

    out.update(
        analytic_rms=_rms(stack("analytic_pose", ok)),
        closed_form_rms=_rms(stack("closed_form_pose", ok)) if all("closed_form_pose" in r for r in ok) else None,
        mle_rms=_rms(stack("mle_pose", ok)),
        reported_sigma=np.sqrt(np.mean([np.diag(r["reported_cov"]) for r in ok], axis=0)),  # quadratic mean
        reported_sigma_mean=np.mean([np.sqrt(np.diag(r["reported_cov"])) for r in ok], axis=0),
        crb_sigma=np.sqrt(np.mean([np.diag(r["crb_cov"]) for r in ok], axis=0)),
        iterations_median=float(np.median([r["iterations"] for r in ok])),
        converged_fraction=float(np.mean([r["converged"] for r in ok])),
        seconds_mean=float(np.mean([r["seconds"] for r in records])),
    )
    if good:
        mle = stack("mle_pose", good)
        first_order = stack("first_order_pose", good)
        reported = stack("reported_cov", good)
        crb = stack("crb_cov", good)
        out.update(
            mle_rms_global=_rms(mle),
            first_order_rms=_rms(first_order),
            reported_sigma_global=np.sqrt(np.mean([np.diag(P) for P in reported], axis=0)),
            crb_sigma_global=np.sqrt(np.mean([np.diag(P) for P in crb], axis=0)),
            nees_reported=float(np.mean(nees(mle, reported))),
            nees_crb=float(np.mean(nees(mle, crb))),
            nees_first_order=float(np.mean(nees(first_order, crb))),
            nees_band=nees_band(len(good)),
        )
        crb_sigma_runs = np.sqrt(np.array([np.diag(P) for P in crb]))
        reported_sigma_runs = np.sqrt(np.array([np.diag(P) for P in reported]))
        # Per-run normalized errors: each run's error over its own sigma (geometries differ between runs,
        # which makes the plain RMS ratio noisier: fewer effective runs).
        out["efficiency_normalized"] = _rms(mle / crb_sigma_runs)
        out["consistency_normalized"] = 1.0 / _rms(mle / reported_sigma_runs)
        out["efficiency"] = out["mle_rms_global"] / out["crb_sigma_global"]
        out["efficiency_first_order"] = out["mle_rms_global"] / out["first_order_rms"]
        out["consistency"] = out["reported_sigma_global"] / out["mle_rms_global"]
        # Control variate (module docstring): unbiased MSE of the MLE with the sampling noise cancelled.
        mse_cv = np.mean(np.array([np.diag(P) for P in crb]), axis=0) + np.mean(mle**2 - first_order**2, axis=0)
        out["mle_rms_cv"] = np.sqrt(np.maximum(mse_cv, 0.0))
        out["efficiency_cv"] = out["mle_rms_cv"] / out["crb_sigma_global"]
        out["consistency_cv"] = out["reported_sigma_global"] / out["mle_rms_cv"]
    if "worst_point" in ok[0]:
        out.update(
            point_analytic_rms=_rms(stack("analytic_point", ok)),
            point_closed_form_rms=(_rms(stack("closed_form_point", ok))
                                   if all("closed_form_point" in r for r in ok) else None),
            point_mle_rms=_rms(stack("mle_point", ok)),
            point_crb_sigma=np.sqrt(np.mean(stack("crb_point_var", ok), axis=0)),
            point_reported_sigma=np.sqrt(np.mean(stack("reported_point_var", ok), axis=0)),
            point_analytic_max_norm_rms=float(_rms(stack("analytic_point_max_norm", ok))),
            point_mle_max_norm_rms=float(_rms(stack("mle_point_max_norm", ok))),
        )
        if good:
            out.update(
                point_mle_rms_global=_rms(stack("mle_point", good)),
                point_first_order_rms=_rms(stack("first_order_point", good)),
                point_crb_sigma_global=np.sqrt(np.mean(stack("crb_point_var", good), axis=0)),
                point_reported_sigma_global=np.sqrt(np.mean(stack("reported_point_var", good), axis=0)),
            )
    return out


def worst_axis(values: np.ndarray) -> tuple[float, float]:
    """Least-accurate-axis values of a 6-vector: (rotation in degrees, position in metres)."""
    return float(np.degrees(np.max(values[:3]))), float(np.max(values[3:]))


def sweep_points(sigmas=SIGMAS_PX, distances=DISTANCES_M, base_sigma=BASE_SIGMA_PX, base_distance=BASE_DISTANCE_M):
    """``[(sweep, sigma_px, distance_m)]``: sweep "a" over sigma at ``base_distance``, "b" over distance."""
    return [("a", s, base_distance) for s in sigmas] + [("b", base_sigma, d) for d in distances]


def csv_rows(records: list[dict], points: list[tuple[str, float, float]]) -> list[dict]:
    """One row per sweep point with every statistic (rotation in degrees, lengths in metres)."""
    by_key = defaultdict(list)
    for r in records:
        by_key[(r["sigma_px"], r["distance_m"])].append(r)
    rows = []
    for sweep, sigma, distance in points:
        stats = summarize(by_key.get((sigma, distance), []))
        row = {"sweep": sweep, "sigma_px": sigma, "distance_m": distance,
               "runs_ok": stats["runs_ok"], "runs_singular": stats["runs_singular"],
               "runs_global": stats.get("runs_global", 0), "runs_local_minimum": stats.get("runs_local_minimum", 0),
               "local_minimum_seeds": " ".join(str(x) for x in stats.get("local_minimum_seeds", []))}
        pose_series = ("analytic_rms", "closed_form_rms", "mle_rms", "reported_sigma", "reported_sigma_mean", "crb_sigma",
                       "mle_rms_global", "mle_rms_cv", "first_order_rms", "reported_sigma_global", "crb_sigma_global")
        for name in pose_series:
            if stats.get(name) is None:
                continue
            rot, pos = worst_axis(stats[name])
            row[f"{name}_rot_worst_deg"] = rot
            row[f"{name}_pos_worst_m"] = pos
            for k, axis in enumerate(AXES):
                row[f"{name}_rot_{axis}_deg"] = float(np.degrees(stats[name][k]))
            for k, axis in enumerate(AXES):
                row[f"{name}_pos_{axis}_m"] = float(stats[name][3 + k])
        for name in ("efficiency", "efficiency_first_order", "consistency", "efficiency_normalized",
                     "consistency_normalized", "efficiency_cv", "consistency_cv"):
            if name not in stats:
                continue
            for k, label in enumerate([f"rot_{a}" for a in AXES] + [f"pos_{a}" for a in AXES]):
                row[f"{name}_{label}"] = float(stats[name][k])
            row[f"{name}_max"] = float(np.max(stats[name]))
            row[f"{name}_min"] = float(np.min(stats[name]))
        if "nees_reported" in stats:
            row["nees_reported_mean"] = stats["nees_reported"]
            row["nees_crb_mean"] = stats["nees_crb"]
            row["nees_first_order_mean"] = stats["nees_first_order"]
            row["nees_band95_lo"], row["nees_band95_hi"] = stats["nees_band"]
        if stats["runs_ok"]:
            row["lm_iterations_median"] = stats["iterations_median"]
            row["lm_converged_fraction"] = stats["converged_fraction"]
            row["seconds_per_run"] = stats["seconds_mean"]
        for name in ("point_analytic_rms", "point_closed_form_rms", "point_mle_rms", "point_reported_sigma", "point_crb_sigma",
                     "point_mle_rms_global", "point_first_order_rms", "point_reported_sigma_global",
                     "point_crb_sigma_global"):
            if stats.get(name) is None:
                continue
            row[f"{name}_worst_m"] = float(np.max(stats[name]))
            for k, axis in enumerate(AXES):
                row[f"{name}_{axis}_m"] = float(stats[name][k])
        if "point_analytic_max_norm_rms" in stats:
            row["point_analytic_max_norm_rms_m"] = stats["point_analytic_max_norm_rms"]
            row["point_mle_max_norm_rms_m"] = stats["point_mle_max_norm_rms"]
        rows.append(row)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row if k not in fields]
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)


# --- figure -----------------------------------------------------------------------------------------


def plot(rows: list[dict], path: Path, title: str, log_scale: bool = True) -> None:
    """Fig. 4's layout: (a), (b) position over attitude vs pixel sigma / distance; (c), (d) worst point.

    ``log_scale``: logarithmic y axes (the paper's are linear; here the analytical errors are often
    ten times the MLE's, which would flatten the MLE and bound curves).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, 11.5), layout="constrained")
    grid = fig.add_gridspec(3, 2)
    series = [
        ("closed_form_rms", "Closed form (Sects. 4-5) RMS error", dict(color="tab:cyan", marker=".", ls=":")),
        ("analytic_rms", "Analytical (closed form + subtree LM) RMS error", dict(color="tab:blue", marker="o", ls="-")),
        ("mle_rms", "MLE RMS error", dict(color="tab:red", marker="s", ls="-")),
        ("mle_rms_global", "MLE RMS error, runs at the global optimum",
         dict(color="tab:red", marker="", ls="--", alpha=0.6)),
        ("reported_sigma", "MLE reported 1σ (mean)", dict(color="tab:green", marker="^", ls="--")),
        ("crb_sigma", "Cramér-Rao 1σ", dict(color="black", marker="", ls=":")),
    ]
    for col, (sweep, xlabel, xkey, letter) in enumerate(
        [("a", "Pixel σ", "sigma_px", "(a)"), ("b", "Mirror distance (m)", "distance_m", "(b)")]
    ):
        sub = [r for r in rows if r["sweep"] == sweep and r["runs_ok"]]
        if not sub:  # this sweep was not run
            continue
        x = [r[xkey] for r in sub]
        ax_pos = fig.add_subplot(grid[0, col])
        ax_att = fig.add_subplot(grid[1, col], sharex=ax_pos)
        for key, label, style in series:
            ax_pos.plot(x, [r.get(f"{key}_pos_worst_m", np.nan) for r in sub], label=label, **style)
            ax_att.plot(x, [r.get(f"{key}_rot_worst_deg", np.nan) for r in sub], label=label, **style)
        ax_pos.set_ylabel("Position (m)")
        ax_att.set_ylabel("Attitude (deg)")
        ax_att.set_xlabel(xlabel)
        ax_pos.set_title(f"{letter} camera-to-base, least-accurate axis", fontsize=10)
        for ax in (ax_pos, ax_att):
            _scale(ax, log_scale)
        ax_pt = fig.add_subplot(grid[2, col])
        if sub and "point_mle_rms_worst_m" in sub[0]:
            for key, label, style in series:
                ax_pt.plot(x, [r.get(f"point_{key}_worst_m", np.nan) for r in sub], label=label, **style)
        ax_pt.set_ylabel("Position (m)")
        ax_pt.set_xlabel(xlabel)
        _scale(ax_pt, log_scale)
        ax_pt.set_title(f"{'(c)' if col == 0 else '(d)'} least-accurately reconstructed point", fontsize=10)
    if fig.axes:
        handles, labels = fig.axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=9)
    fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def fig_title(rows: list[dict], num_images: int, num_points: int) -> str:
    ok = [r["runs_ok"] for r in rows]
    singular = sum(r["runs_singular"] for r in rows)
    minima = sum(r.get("runs_local_minimum", 0) for r in rows)
    count = f"{min(ok)}" if min(ok) == max(ok) else f"{min(ok)}-{max(ok)}"
    return (f"Two-mirror base case ({num_images} images, {num_points} points): {count} non-singular Monte Carlo "
            f"runs per point ({singular} singular, {minima} LM local minima in all)")


def _scale(ax, log_scale: bool) -> None:
    if log_scale:
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    else:
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)


# --- driver -----------------------------------------------------------------------------------------


#: The fields that name one run in the log (a run is kept once per key).
TRIAL_KEY = ("sigma_px", "distance_m", "seed", "num_images", "num_points")


def _key(record_or_task: dict) -> tuple:
    return tuple(record_or_task[field] for field in TRIAL_KEY)


def run_sweep(
    points: list[tuple[str, float, float]],
    runs: int,
    num_images: int,
    num_points: int,
    jobs: int,
    log_path: Path | None = None,
    time_budget_s: float | None = None,
    progress: bool = True,
    fresh: bool = False,
) -> list[dict]:
    """Every run of every sweep point (shared points run once), resumed from and appended to ``log_path``
    (a ``TrialLog``: locked while this runs; ``fresh``: emptied first).

    Runs go seed-major (run 0 of every point, then run 1, ...), so a ``time_budget_s`` that stops
    submitting early leaves every point with about the same number of runs.
    """

    with TrialLog(log_path, TRIAL_KEY, fresh=fresh) as log:
        return _run_sweep(log, points, runs, num_images, num_points, jobs, time_budget_s, progress)


def _run_sweep(log: TrialLog, points, runs, num_images, num_points, jobs, time_budget_s, progress) -> list[dict]:
    done = [r for r in log.records if r["num_images"] == num_images and r["num_points"] == num_points]
    have = {_key(r) for r in done}
    unique = list(dict.fromkeys((s, d) for _, s, d in points))
    tasks = [
        dict(sigma_px=s, distance_m=d, seed=seed, num_images=num_images, num_points=num_points)
        for seed in range(runs)
        for s, d in unique
    ]
    todo = [t for t in tasks if _key(t) not in have]
    wanted = {_key(t) for t in tasks}
    records = [r for r in done if _key(r) in wanted]
    run_trials(run_trial, todo, records, total=len(tasks), log=log, desc="Monte Carlo runs",
               progress=progress, jobs=jobs, time_budget_s=time_budget_s)
    return records


#: Wall time of one run at the default size (200 images, 60 points) on one worker, seconds: 1300 runs
#: (``--runs 100``, 13 sweep points) took about 2 h with ``--jobs 2`` on the project's shared 2-core
#: machine. A run's time grows about linearly with the images.
SECONDS_PER_RUN = 11.0


def time_estimate(points: list[tuple[str, float, float]], runs: int, num_images: int, jobs: int) -> str:
    """One line: how many runs the sweep holds and about how long they take (:data:`SECONDS_PER_RUN`), with
    the way to bound it (``--time-budget``)."""
    unique = len(dict.fromkeys((s, d) for _, s, d in points))
    total = unique * runs
    seconds = total * SECONDS_PER_RUN * (num_images / 200.0) / max(jobs, 1)
    span = f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"
    return (f"reproduce_fig4: {total} runs ({unique} sweep points x {runs}) on {jobs} worker(s): about {span} at "
            f"~{SECONDS_PER_RUN:g} s per run of {num_images} images (measured on a 2-core machine; runs already in "
            "OUT/runs.jsonl are not repeated). --time-budget MIN stops starting runs after MIN minutes and reports "
            "what finished (--runs 10 takes a tenth)")


def _parse_list(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(",") if x.strip())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100, help="Monte Carlo runs per sweep point (default 100)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: all cores)")
    parser.add_argument("--images", type=int, default=200, help="images per run (default 200)")
    parser.add_argument("--points", type=int, default=60, help="reconstruction points per run (default 60)")
    parser.add_argument("--sigmas", type=_parse_list, default=SIGMAS_PX, help="pixel sigmas of sweep (a), comma-separated")
    parser.add_argument("--distances", type=_parse_list, default=DISTANCES_M,
                        help="mirror distances (m) of sweep (b), comma-separated")
    parser.add_argument("--out", type=Path, default=Path("out/fig4"), help="output directory (default out/fig4)")
    parser.add_argument("--fresh", action="store_true", help="ignore runs already in OUT/runs.jsonl (delete it)")
    parser.add_argument("--time-budget", type=float, default=None, metavar="MIN",
                        help="stop starting new runs after MIN minutes; report what finished")
    parser.add_argument("--linear", action="store_true", help="linear y axes, as in the paper (default: log)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def format_summary(rows: list[dict]) -> str:
    """A plain-text table of the figure's numbers and the efficiency / consistency / NEES checks."""
    lines = [
        "Fig. 4 numbers: least-accurate axis, RMS over the non-singular runs (rotation deg, position mm)",
        "sweep sigma_px dist_m runs | closed form rot pos | analytic rot pos | MLE rot pos | reported 1s rot pos"
        " | CRB 1s rot pos | worst point mm: closed form, analytic, MLE, CRB",
    ]
    for r in rows:
        head = f"  {r['sweep']}  {r['sigma_px']:5.2f}  {r['distance_m']:5.2f} {r['runs_ok']:4d}"
        if not r["runs_ok"]:
            lines.append(head + "  no successful run")
            continue
        point = ""
        if "point_mle_rms_worst_m" in r:
            point = (f"{1000 * r.get('point_closed_form_rms_worst_m', np.nan):6.1f} "
                     f"{1000 * r['point_analytic_rms_worst_m']:6.1f} {1000 * r['point_mle_rms_worst_m']:5.1f} "
                     f"{1000 * r['point_crb_sigma_worst_m']:5.1f}")
        lines.append(
            f"{head} | {r.get('closed_form_rms_rot_worst_deg', np.nan):6.3f} "
            f"{1000 * r.get('closed_form_rms_pos_worst_m', np.nan):6.1f} | "
            f"{r['analytic_rms_rot_worst_deg']:6.3f} {1000 * r['analytic_rms_pos_worst_m']:6.1f} | "
            f"{r['mle_rms_rot_worst_deg']:6.3f} {1000 * r['mle_rms_pos_worst_m']:6.1f} | "
            f"{r['reported_sigma_rot_worst_deg']:6.3f} {1000 * r['reported_sigma_pos_worst_m']:6.1f} | "
            f"{r['crb_sigma_rot_worst_deg']:6.3f} {1000 * r['crb_sigma_pos_worst_m']:6.1f} | {point}"
        )
    lines += [
        "",
        "MLE checks over the runs at the global optimum, per axis: efficiency MLE RMS / CRB 1s (max; [per-run",
        "normalized]; (MLE RMS / first-order estimator RMS on the same noise); {control variate}), consistency",
        "reported 1s / MLE RMS (min-max; [per-run normalized]; {control variate}), mean pose NEES with the",
        "reported covariance (95 % band)",
        "sweep sigma_px dist_m global/ok | eff max [norm] (1st-ord) {cv} | cons min-max [norm] {cv} | NEES (band) | local minima",
    ]
    for r in rows:
        if not r.get("runs_global"):
            continue
        minima = f"seeds {r['local_minimum_seeds']}" if r["runs_local_minimum"] else "none"
        singular = f" +{r['runs_singular']} singular" if r["runs_singular"] else ""
        lines.append(
            f"  {r['sweep']}  {r['sigma_px']:5.2f}  {r['distance_m']:5.2f} {r['runs_global']}/{r['runs_ok']}"
            f"{singular} | {r['efficiency_max']:.3f} [{r['efficiency_normalized_max']:.3f}] "
            f"({r['efficiency_first_order_max']:.3f}) {{{r['efficiency_cv_max']:.3f}}} | "
            f"{r['consistency_min']:.3f}-{r['consistency_max']:.3f} "
            f"[{r['consistency_normalized_min']:.3f}-{r['consistency_normalized_max']:.3f}] "
            f"{{{r['consistency_cv_min']:.3f}-{r['consistency_cv_max']:.3f}}} | "
            f"{r['nees_reported_mean']:.2f} ({r['nees_band95_lo']:.2f}-{r['nees_band95_hi']:.2f}) | {minima}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    log_path = args.out / "runs.jsonl"
    points = sweep_points(args.sigmas, args.distances)
    print(time_estimate(points, args.runs, args.images, args.jobs), flush=True)  # on stdout: stderr is for the one-line error
    start = time.perf_counter()
    records = run_sweep(
        points, args.runs, args.images, args.points, args.jobs, log_path,
        None if args.time_budget is None else 60.0 * args.time_budget, progress=not args.no_progress,
        fresh=args.fresh,
    )
    rows = csv_rows(records, points)
    write_csv(args.out / "fig4.csv", rows)
    title = fig_title(rows, args.images, args.points)
    plot(rows, args.out / "fig4.png", title, log_scale=not args.linear)
    print(format_summary(rows))
    print(f"wrote {args.out / 'fig4.csv'}, {args.out / 'fig4.png'} ({len(records)} runs in the log, "
          f"{time.perf_counter() - start:.0f} s this time)")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
