#!/usr/bin/env python
"""Speed and memory of a calibration, in one run on this machine.

    python scripts/benchmark.py [--repeats 5] [--slow-repeats 3] [--quick] [--profile] [--json out.json]
    python scripts/benchmark.py --scaling [--scaling-max 10000]   # time per stage and memory, 1k..100k images
    python scripts/benchmark.py --startup [--peer DIR]   # --version, calibrate's start-up, beside Takahashi 2012
    python scripts/benchmark.py --rig   # three-camera rig, 480 and 4,800 images, beside the tree at 4,800

Problems (simulator, Sect. 7): two mirrors, 3 fiducials, 1 px; (a) 900 images, mirror 1 in three
placements of 300, mirror 2 moving every image; (b) 200 images with 60 reconstruction points.
Printed, medians of repeated runs:
1. ``calibrate()`` time (analytical + build + LM + marginals), fast path and per-measurement reference;
2. one linearisation of the measurement factors in us per measurement (and one ``error()``), beside
   GTSAM's native ``GenericProjectionFactorCal3_S2`` on a graph of as many factors (the native floor),
   and one Levenberg-Marquardt iteration of each inside GTSAM;
3. the same problems with ``scipy.optimize.least_squares`` (sparse Jacobian structure given, finite
   differences) from the same analytical start, plus a covariance by inverting ``J^T J``;
4. peak resident memory (``ru_maxrss``) of each, every case in its own subprocess;
5. (200 images + 60 points) the LM stage against a dense numpy LM (:func:`dense_lm`) from the same start,
   alternating in one process: goal <= 0.25x.
``--startup`` times ``mirror-fg --version`` and the start-up of ``calibrate`` on the embedded example, and,
given a checkout of AbdirayimovS/takahashi2012cvpr (``--peer``), both solvers on the same 5 photographs.
``--profile`` adds a pyinstrument profile of one fast calibration per problem, and ``--native-profile``
a py-spy profile with native frames that splits the time inside GTSAM (pip install '.[bench]').
The machine is shared: wall and CPU time and the load average are printed to show contention.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))  # the tree's own factors (tests/reference/)

CASES = {
    "900img": {
        "title": "900 images, 3 fiducials (mirror 1: 3 x 300 images, mirror 2 moving)",
        "simulate": {"num_images": 900, "num_points": 0, "mirror1_placements": 3},
    },
    "200img+60pts": {
        "title": "200 images, 3 fiducials + 60 reconstruction points",
        "simulate": {"num_images": 200, "num_points": 60, "mirror1_placements": 3},
        "oracle": True,  # the LM stage timed against dense_lm (795 unknowns: a dense J^T J is affordable)
    },
}
COMMON = {"pixel_sigma": 1.0, "mirror_distance": 0.5, "tilt_deg": 30.0, "seed": 0, "num_mirrors": 2, "num_fiducials": 3}
GOALS = {"900img": 0.5, "200img+60pts": 1.0}  # seconds, calibrate() total
ORACLE_GOAL = 0.25  # LM stage / dense numpy LM (dense_lm), measured alternately in one process
LINEARISE_GOAL = 2.0  # x the native floor per measurement
SPEEDUP_GOAL = 10.0  # x faster than scipy
MEMORY_GOAL_MB = 1024.0  # 900-image problem with marginals


# --------------------------------------------------------------------------------------------------
# Worker side: one task of one problem, in its own process (peak memory per task).


def _dataset(case: str):
    from mirror_fg.simulate.tree import simulate_base_case

    return simulate_base_case(**CASES[case]["simulate"], **COMMON)


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def _estimate(cal) -> dict:
    return {"R": cal.R_cam_base.tolist(), "t": cal.t_cam_base.tolist(), "final_error": cal.final_error, "iterations": cal.iterations}


def task_baseline(case: str, repeats: int) -> dict:
    """Interpreter + gtsam + numpy + the dataset: the memory floor of every other task."""
    import gtsam  # noqa: F401

    from mirror_fg.solver.model.graph import measurements_of

    dataset, _ = _dataset(case)
    measurements_of(dataset)
    return {"peak_mb": _peak_mb()}


def task_calibrate(case: str, repeats: int, fast: bool) -> dict:
    from mirror_fg import calibrate

    dataset, _ = _dataset(case)
    runs = []
    mode = "calibrate(fast=True): the last mirror eliminated (factors/view_eliminated.py)" if fast else "calibrate(fast=False): one ViewFactor per image"
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        cal = calibrate(dataset, fast=fast)
        runs.append({"wall": time.perf_counter() - start_wall, "cpu": time.process_time() - start_cpu, **cal.timings})
    summary = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    return {"mode": mode, "median": summary, "runs": runs, "estimate": _estimate(cal), "peak_mb": _peak_mb()}


def _native_graph(num_images: int, points_per_image: int, rng: np.random.Generator):
    """GTSAM-native projection factors, one per measurement: image i sees landmark j (pixels, 1 px)."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    K = gtsam.Cal3_S2(800.0, 800.0, 0.0, 512.0, 384.0)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    landmarks = np.column_stack([rng.uniform(-0.3, 0.3, (points_per_image, 2)), rng.uniform(1.8, 2.2, points_per_image)])
    for j, p in enumerate(landmarks):
        values.insert(L(j), p)
    for i in range(num_images):
        pose = gtsam.Pose3(gtsam.Rot3.RzRyRx(*(0.05 * rng.normal(size=3))), 0.05 * rng.normal(size=3))
        values.insert(X(i), pose)
        camera = gtsam.PinholeCameraCal3_S2(pose, K)
        for j, p in enumerate(landmarks):
            graph.add(gtsam.GenericProjectionFactorCal3_S2(camera.project(p) + rng.normal(size=2), noise, X(i), L(j), K))
    return graph, values


def _nudged(values, scale: float = 1e-7):
    """A second set of values (a tiny retraction), so each timed pass evaluates new values."""
    import gtsam

    delta = gtsam.VectorValues()
    zero = values.zeroVectors()
    for key in values.keys():
        delta.insert(key, np.full(zero.at(key).shape[0], scale))
    return values.retract(delta)


def task_linearize(case: str, repeats: int) -> dict:
    """us per measurement of linearize() and error() at new values, and of one LM iteration: the one model's
    graph as calibrate() solves it (each photograph's own placement eliminated inside the stacked view
    factors), its per-image view factors, and GTSAM's native projection factors as the floor."""
    import gtsam

    from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem

    dataset, truth = _dataset(case)
    problem = ViewProblem(dataset)
    estimate = ViewEstimate({SINGLE_CAMERA: (truth.R_cam_base, truth.t_cam_base)}, dict(truth.mirror_vectors),
                            dict(truth.points))
    fast, fast_values, _ = problem.solve_graph(estimate, True)
    stacked = problem.graph(stacked=True)  # every placement a variable
    reference = problem.graph(stacked=False)
    values = _nudged(problem.values(estimate), 1e-4)  # off the optimum
    fast_values = _nudged(fast_values, 1e-4)
    count = sum(len(image.observations) for image in dataset.images)
    per_image = count // len(dataset.images)
    native, native_values = _native_graph(len(dataset.images), per_image, np.random.default_rng(0))
    assert native.size() == count
    passes = max(repeats, 3) * 4
    graphs = {"native": (native, native_values), "stacked": (stacked, values), "fast": (fast, fast_values),
              "reference": (reference, values)}
    # Four sets of values used in turn: every timed call meets values the previous call did not see.
    cycles = {name: [vals] + [_nudged(vals, 1e-7 * k) for k in (1, 2, 3)] for name, (_, vals) in graphs.items()}

    def lm_iteration(graph, vals):
        gtsam.LevenbergMarquardtOptimizer(graph, vals, gtsam.LevenbergMarquardtParams()).iterate()

    # Native and batched passes interleaved, so that both see the same contention on a shared machine.
    samples: dict[str, dict[str, list[float]]] = {name: {"linearize": [], "error": [], "lm": []} for name in graphs}
    for i in range(passes):
        for name in graphs:
            if name == "reference" and i % 5:
                continue  # ~50x slower: fewer passes
            graph, cycle = graphs[name][0], cycles[name]
            for what, run in (
                ("linearize", lambda: graph.linearize(cycle[(3 * i) % 4])),
                ("error", lambda: graph.error(cycle[(3 * i + 1) % 4])),
                ("lm", lambda: lm_iteration(graph, cycle[(3 * i + 2) % 4])),
            ):
                if what == "lm" and i % 3:
                    continue
                start = time.process_time()
                run()
                samples[name][what].append(time.process_time() - start)
    results = {
        name: {
            "factors": graphs[name][0].size(),
            "linearize_us": 1e6 * float(np.median(s["linearize"])) / count,
            "error_us": 1e6 * float(np.median(s["error"])) / count,
            "lm_iteration_us": 1e6 * float(np.median(s["lm"])) / count,
        }
        for name, s in samples.items()
    }
    return {"measurements": count, "results": results, "peak_mb": _peak_mb()}


def _scipy_problem(dataset, initial):
    """Residuals (whitened, vectorised numpy), sparsity and start of the problem for least_squares."""
    import scipy.sparse as sparse
    from scipy.spatial.transform import Rotation

    from mirror_fg.solver.model.graph import measurements_of

    measurements = measurements_of(dataset)
    configs = sorted(dataset.configurations)
    config_index = {c: i for i, c in enumerate(configs)}
    names = dataset.reconstruction_point_names
    point_index = {n: i for i, n in enumerate(names)}
    mirror = np.array([[config_index[(l + 1, m)] for l, m in enumerate(meas.mirror_configs)] for meas in measurements])
    landmark = np.array([point_index.get(meas.point, -1) for meas in measurements])
    fiducial = np.array([dataset.fiducials.get(meas.point, np.zeros(3)) for meas in measurements])
    observed = np.array([meas.normalized for meas in measurements])
    sigma = dataset.normalized_sigma
    is_landmark = landmark >= 0
    R0 = np.asarray(initial.R_cam_base)
    n_configs = len(configs)
    x0 = np.concatenate(
        [np.zeros(3), initial.t_cam_base]
        + [initial.mirror_vectors[c] for c in configs]
        + [initial.points[n] for n in names]
    )

    def unpack(x):
        R = R0 @ Rotation.from_rotvec(x[:3]).as_matrix()  # R0 Exp(w)
        return R, x[3:6], x[6 : 6 + 3 * n_configs].reshape(-1, 3), x[6 + 3 * n_configs :].reshape(-1, 3)

    def residuals(x):
        R, t, V, P = unpack(x)
        base = fiducial.copy()
        base[is_landmark] = P[landmark[is_landmark]]
        p = base @ R.T + t  # eq. (2)
        for level in range(mirror.shape[1]):  # eq. (3)
            v = V[mirror[:, level]]
            vv = np.einsum("ij,ij->i", v, v)
            p = p - v * (2.0 * (np.einsum("ij,ij->i", v, p) - vv) / vv)[:, None]
        return ((p[:, :2] / p[:, 2:3] - observed) / sigma).ravel()  # eq. (9), whitened

    rows, cols = [], []
    for i in range(len(measurements)):
        columns = list(range(6)) + [6 + 3 * mirror[i, k] + d for k in range(mirror.shape[1]) for d in range(3)]
        if landmark[i] >= 0:
            columns += [6 + 3 * n_configs + 3 * landmark[i] + d for d in range(3)]
        for r in (2 * i, 2 * i + 1):
            rows += [r] * len(columns)
            cols += columns
    sparsity = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * len(measurements), len(x0)))
    return residuals, sparsity, x0, unpack


def task_scipy(case: str, repeats: int) -> dict:
    from scipy.optimize import least_squares

    from mirror_fg import initial_estimate

    dataset, _ = _dataset(case)
    runs = []
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        initial = initial_estimate(dataset)  # the same start as calibrate()
        analytic = time.perf_counter() - start_wall
        start = time.perf_counter()
        residuals, sparsity, x0, unpack = _scipy_problem(dataset, initial)
        build = time.perf_counter() - start
        start = time.perf_counter()
        # Exact-enough LSMR steps: with its default tolerances (1e-6) trf crawls (thousands of evaluations).
        result = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", tr_options={"atol": 1e-12, "btol": 1e-12})
        solve = time.perf_counter() - start
        start = time.perf_counter()
        J = result.jac
        covariance = np.linalg.inv((J.T @ J).toarray())  # every block's covariance, as a user would
        marginals = time.perf_counter() - start
        runs.append({
            "analytic": analytic, "build": build, "optimize": solve, "marginals": marginals,
            "wall": time.perf_counter() - start_wall, "cpu": time.process_time() - start_cpu,
        })
    R, t, _, _ = unpack(result.x)
    summary = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
    return {
        "median": summary, "runs": runs, "nfev": int(result.nfev), "status": int(result.status),
        "final_error": float(0.5 * result.fun @ result.fun), "covariance_dim": int(covariance.shape[0]),
        "estimate": {"R": R.tolist(), "t": np.asarray(t).tolist()}, "peak_mb": _peak_mb(),
    }


def _column_groups(sparsity) -> list[np.ndarray]:
    """Columns in groups that share no row (greedy colouring of the sparsity pattern): one residual
    evaluation per group gives every column of the group's forward difference."""
    csc = sparsity.tocsc()
    used: list[np.ndarray] = []
    groups: list[list[int]] = []
    for column in range(csc.shape[1]):
        rows = csc.indices[csc.indptr[column] : csc.indptr[column + 1]]
        for color, taken in enumerate(used):
            if not taken[rows].any():
                break
        else:
            color = len(used)
            used.append(np.zeros(csc.shape[0], dtype=bool))
            groups.append([])
        used[color][rows] = True
        groups[color].append(column)
    return [np.array(g) for g in groups]


def dense_lm(residuals, sparsity, x0: np.ndarray, max_iterations: int = 100) -> tuple[np.ndarray, int, float]:
    """The oracle the LM stage is timed against: textbook Levenberg-Marquardt in dense numpy on the same
    whitened residuals (eq. 23). Jacobian by forward differences in column groups (:func:`_column_groups`),
    dense ``J^T J``, Marquardt's damping ``lambda diag(J^T J)``, Cholesky solve; stops when a step lowers
    the cost by less than 1e-10 relative. Returns ``(x, iterations, cost)``."""
    groups = _column_groups(sparsity)
    pattern = sparsity.toarray().astype(bool)
    x, r = x0.copy(), residuals(x0)
    cost, damping = 0.5 * float(r @ r), 1e-5
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        J = np.zeros((len(r), len(x)))
        for group in groups:
            h = 1.5e-8 * np.maximum(1.0, np.abs(x[group]))
            probe = x.copy()
            probe[group] += h
            difference = residuals(probe) - r
            for column, step in zip(group, h):
                rows = pattern[:, column]
                J[rows, column] = difference[rows] / step
        JtJ, gradient = J.T @ J, J.T @ r
        while True:
            A = JtJ + damping * np.diag(np.diag(JtJ))
            try:
                step = -np.linalg.solve(A, gradient)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            r_new = residuals(x + step)
            cost_new = 0.5 * float(r_new @ r_new)
            if cost_new < cost:
                break
            damping *= 10.0
            if damping > 1e10:
                return x, iterations, cost
        decrease = cost - cost_new
        x, r, cost, damping = x + step, r_new, cost_new, max(damping / 10.0, 1e-12)
        if decrease < 1e-10 * cost:
            break
    return x, iterations, cost


def task_oracle(case: str, repeats: int) -> dict:
    """The LM stage beside :func:`dense_lm` from the same start, alternating in one process (the same
    contention for both): ``calibrate()``'s ``optimize`` time over the oracle's LM time."""
    from mirror_fg import calibrate, initial_estimate

    dataset, _ = _dataset(case)
    initial = initial_estimate(dataset)
    residuals, sparsity, x0, unpack = _scipy_problem(dataset, initial)
    ours, oracle = [], []
    for _ in range(repeats):
        cal = calibrate(dataset, initial=initial)
        ours.append(cal.timings["optimize"])
        start = time.perf_counter()
        x, iterations, cost = dense_lm(residuals, sparsity, x0)
        oracle.append(time.perf_counter() - start)
    ratios = [a / b for a, b in zip(ours, oracle)]
    return {"optimize": float(np.median(ours)), "oracle": float(np.median(oracle)), "ratio": float(np.median(ratios)),
            "iterations": int(cal.iterations), "oracle_iterations": iterations, "final_error": cal.final_error,
            "oracle_final_error": cost, "unknowns": int(len(x0)), "load": os.getloadavg()[0]}


def task_profile(case: str, repeats: int) -> dict:
    try:
        from pyinstrument import Profiler
    except ImportError:
        return {"text": "pyinstrument is not installed (pip install pyinstrument)"}
    from mirror_fg import calibrate

    dataset, _ = _dataset(case)
    profiler = Profiler(interval=0.001)
    profiler.start()
    calibrate(dataset)
    profiler.stop()
    text = profiler.output_text(unicode=False, color=False, show_all=False)
    return {"text": text}


def task_loop(case: str, repeats: int) -> dict:
    """``repeats`` fast calibrations, for a sampling profiler to watch."""
    from mirror_fg import calibrate

    dataset, _ = _dataset(case)
    for _ in range(repeats):
        calibrate(dataset)
    return {}


#: Where a native stack sample inside ``calibrate()`` is counted: the first rule one of whose frame names
#: (``|`` between alternatives) occurs in the stack (``*`` rules only inside an LM run, subtree or main;
#: ``!`` rules only outside one).
_NATIVE_RULES = [
    ("marginals (Schur complement, GTSAM Marginals)", "marginal_covariances|eliminated_covariances ("),
    ("graph building (factors, initial values)", "build_graph|build_eliminated_graph ("),
    ("initial estimate: PnP and closed form (numpy, OpenCV)", "!solve_analytic|initial_estimate ("),
    ("{lm}: our Python factors (error and Jacobians)", "*CustomFactor::unwhitenedError"),
    ("{lm}: GTSAM forms the Hessian of each dense factor", "*JacobianFactor::updateHessian"),
    ("{lm}: GTSAM Cholesky elimination (the rest)", "*eliminate"),
    ("{lm}: GTSAM other (Values, damping, error sums)", "*LevenbergMarquardtOptimizer"),
    ("main LM: Gauss-Newton polish and stall test (factors, elimination)", "_polished (|_stationary ("),
    ("residual statistics and the rest (Python)", ""),
]


def _matches(rule: str, stack: str) -> bool:
    return any(name in stack for name in rule.split("|"))


def native_breakdown(raw: str) -> list[tuple[str, float]]:
    """Shares of ``calibrate()`` time per :data:`_NATIVE_RULES` from py-spy's raw (collapsed) output."""
    counts: dict[str, int] = {}
    total = 0
    for line in raw.splitlines():
        stack, _, number = line.rpartition(" ")
        if "calibrate (" not in stack or not number.isdigit():
            continue
        samples = int(number)
        total += samples
        lm = "initial estimate: subtree LM" if "_refine_subtree (" in stack else "main LM"
        in_lm = "LevenbergMarquardtOptimizer" in stack
        for label, rule in _NATIVE_RULES:
            if rule.startswith("*"):
                if in_lm and _matches(rule[1:], stack):
                    break
            elif rule.startswith("!"):
                if _matches(rule[1:], stack) and not in_lm:
                    break
            elif _matches(rule, stack):
                break
        label = label.format(lm=lm)
        counts[label] = counts.get(label, 0) + samples
    return sorted(((k, v / total) for k, v in counts.items()), key=lambda item: -item[1]) if total else []


def native_profile(case: str, repeats: int) -> str:
    """py-spy (``--native``) over ``repeats`` calibrations: the table of :func:`native_breakdown`."""
    import shutil
    import tempfile

    spy = shutil.which("py-spy") or os.path.join(os.path.dirname(sys.executable), "py-spy")
    if not os.path.exists(spy):
        return "py-spy is not installed (pip install '.[bench]')"
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "raw.txt")
        command = [spy, "record", "--native", "--rate", "250", "--format", "raw", "--output", out, "--",
                   sys.executable, os.path.abspath(__file__), "--worker", "loop", case, str(repeats)]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0 or not os.path.exists(out):
            return f"py-spy failed: {done.stderr.strip()[-300:]}"
        with open(out, encoding="utf-8") as handle:
            rows = native_breakdown(handle.read())
    return "\n".join(f"{100 * share:5.1f} %  {label}" for label, share in rows)


def task_scaling(case: str, repeats: int) -> dict:
    """One calibrate() of ``case`` images (2 mirrors, 3 fiducials, mirror 1 in 3 placements): stage times
    and the process's peak memory (each size in a fresh process, so the peak is its own)."""
    from mirror_fg import calibrate
    from mirror_fg.simulate.tree import simulate_base_case

    start = time.perf_counter()
    dataset, _ = simulate_base_case(num_images=int(case), num_points=0, mirror1_placements=3, **COMMON)
    simulate = time.perf_counter() - start
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    cal = calibrate(dataset)
    wall, cpu = time.perf_counter() - start_wall, time.process_time() - start_cpu
    return {"images": int(case), "simulate": simulate, "wall": wall, "cpu": cpu, **cal.timings,
            "iterations": cal.iterations, "converged": bool(cal.converged), "peak_mb": _peak_mb()}


def task_rig(case: str, repeats: int) -> dict:
    """One calibrate() of the three-camera rig with two hand-held mirrors (``case`` ``rig:K``: K shared
    photographs and K own per camera, 16 K images of 4 fiducials) or of the paper's tree (``tree:N``: N
    images, 3 fiducials, as ``--scaling``): wall time, stage times and measurements."""
    from mirror_fg import calibrate
    from mirror_fg.io.dataset import dataset_from_dict
    from mirror_fg.simulate.tree import simulate_base_case
    from mirror_fg.simulate.rig import simulate_rig_mixed

    kind, count = case.split(":")
    if kind == "rig":
        dataset = dataset_from_dict(simulate_rig_mixed(3, own=[int(count)] * 3, shared=int(count), seed=0)[0])
    else:
        dataset, _ = simulate_base_case(num_images=int(count), num_points=0, mirror1_placements=3, **COMMON)
    measurements = sum(len(image.observations) for image in dataset.images)
    walls = []
    for _ in range(repeats):
        start = time.perf_counter()
        cal = calibrate(dataset)
        walls.append(time.perf_counter() - start)
    return {"images": len(dataset.images), "measurements": measurements, "wall": float(np.median(walls)),
            **cal.timings, "iterations": cal.iterations}


#: ``--rig``: the rig's sizes (shared and own photographs per camera: 480 and 4,800 images) and the tree's.
RIG_CASES = ("rig:20", "rig:200", "tree:4800")
RIG_GOALS = {"rig 4,800 / 480 images": 12.0, "rig / tree cost per measurement": 2.0}


def rig_table(repeats: int) -> list[tuple[str, str, bool]]:
    """``--rig``: the three-camera rig (``simulate --kind mixed --cameras 3 --shared K --own K,K,K``) at 480
    and 4,800 images and the tree at 4,800, each in its own process, back to back; the goals' ratios."""
    print(f"rig: 3 cameras, two hand-held mirrors, 4 fiducials, 1 px; the tree: 2 mirrors, 3 fiducials; "
          f"load average {os.getloadavg()[0]:.2f}")
    rows = {}
    for case in RIG_CASES:
        row = _run("rig", case, repeats)
        rows[case] = row
        stages = " ".join(f"{k} {row.get(k, 0.0):.2f}" for k in ("pnp", "screen", "analytic", "build", "optimize", "marginals")
                          if k in row)
        print(f"{case:>10s} {row['images']:6d} images {row['measurements']:7d} measurements  {row['wall']:8.2f} s  "
              f"({stages}; LM it {row['iterations']})", flush=True)
    growth = rows["rig:200"]["wall"] / rows["rig:20"]["wall"]
    per_measurement = ((rows["rig:200"]["wall"] / rows["rig:200"]["measurements"])
                       / (rows["tree:4800"]["wall"] / rows["tree:4800"]["measurements"]))
    return [("rig 4,800 / 480 images", f"{growth:.1f}x", growth <= RIG_GOALS["rig 4,800 / 480 images"]),
            ("rig / tree cost per measurement", f"{per_measurement:.2f}x",
             per_measurement <= RIG_GOALS["rig / tree cost per measurement"])]


#: Image counts of ``--scaling`` (2 mirrors, 3 fiducials).
SCALING_SIZES = (1_000, 3_000, 10_000, 30_000, 100_000)


def scaling_table(max_images: int, timeout_s: float) -> list[dict]:
    """``--scaling``: calibrate() per size in a fresh process; prints the table and the 10k / 1k ratio."""
    stages = ("analytic", "build", "optimize", "marginals", "residuals")
    print(f"scaling: 2 mirrors (mirror 1 in 3 placements, mirror 2 new in every image), 3 fiducials, 1 px; "
          f"one calibrate() per size, each in its own process; load average {os.getloadavg()[0]:.2f}")
    header = f"{'images':>8s} " + " ".join(f"{k:>9s}" for k in stages) + f" {'total':>8s} {'cpu':>8s} {'LM it':>5s} {'peak MB':>8s}"
    print(header)
    rows = []
    for size in (n for n in SCALING_SIZES if n <= max_images):
        command = [sys.executable, os.path.abspath(__file__), "--worker", "scaling", str(size), "1"]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            print(f"{size:8d}  not finished within {timeout_s:.0f} s: stopped")
            break
        lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
        if not lines:
            print(f"{size:8d}  failed (exit {done.returncode}): {done.stderr.strip().splitlines()[-1:] }")
            break
        row = json.loads(lines[0][len("RESULT "):])
        rows.append(row)
        print(f"{size:8d} " + " ".join(f"{row.get(k, 0.0):9.3f}" for k in stages)
              + f" {row['wall']:8.3f} {row['cpu']:8.3f} {row['iterations']:5d} {row['peak_mb']:8.0f}", flush=True)
    by_size = {row["images"]: row for row in rows}
    if 1_000 in by_size and 10_000 in by_size:
        ratio = by_size[10_000]["wall"] / by_size[1_000]["wall"]
        print(f"time(10k) / time(1k) = {ratio:.1f} (goal <= 10: linear; 10k images <= 5 s: "
              f"{by_size[10_000]['wall']:.2f} s)")
    print(f"load average at end {os.getloadavg()[0]:.2f} on {os.cpu_count()} cpus")
    return rows


# --------------------------------------------------------------------------------------------------
# Start-up and a peer: the command's own cost, and a public Python port of Takahashi et al.
# (CVPR 2012: linear solution + scipy bundle adjustment) on the same 5 real photographs.

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The peer: https://github.com/AbdirayimovS/takahashi2012cvpr (python/tnm.py), given with --peer or
#: $MIRROR_FG_PEER as a checkout or a git directory; copied into a temporary directory, never vendored.
PEER = "AbdirayimovS/takahashi2012cvpr"
STARTUP_GOALS = {"version": 0.3, "calibrate": 0.5}  # seconds: `mirror-fg --version`; calibrate's start-up
EXAMPLE = os.path.join(REPO_ROOT, "examples", "base_case.json")


def takahashi_dir() -> str | None:
    """The 5 real photographs' corner data (dataset.json and the peer's text files), if present."""
    for candidate in (os.path.join(REPO_ROOT, "examples", "takahashi2012"),
                      os.path.join(os.path.dirname(REPO_ROOT), "shared", "data", "takahashi2012")):
        if all(os.path.exists(os.path.join(candidate, name)) for name in ("dataset.json", "model.txt", "camera.txt")):
            return candidate
    return None


def peer_checkout(source: str | None, into: str) -> str | None:
    """``into`` holding the peer's ``tnm.py`` (from a checkout or a git directory ``source``), or None."""
    source = source or os.environ.get("MIRROR_FG_PEER")
    if not source:
        return None
    checkout = os.path.join(source, "python", "tnm.py")
    if os.path.isfile(checkout):
        with open(checkout, encoding="utf-8") as handle:
            text = handle.read()
    else:
        shown = subprocess.run(["git", "--git-dir", source, "show", "HEAD:python/tnm.py"], capture_output=True, text=True)
        if shown.returncode != 0:
            return None
        text = shown.stdout
    with open(os.path.join(into, "tnm.py"), "w", encoding="utf-8") as handle:
        handle.write(text)
    return into


#: The peer as a command: its demo without the plots (load the text files, linear solution, bundle adjustment).
_PEER_SCRIPT = """import sys
from ast import literal_eval
import numpy as np
sys.path.insert(0, sys.argv[1])
from tnm import tnm, tnm_ba
data = sys.argv[2]
model = np.loadtxt(f"{data}/model.txt")
q = np.array([np.loadtxt(f"{data}/input{i}.txt") for i in range(1, 6)])
K = np.loadtxt(f"{data}/camera.txt", converters=lambda v: literal_eval(str(v).replace(",", "")))
R0, T0, n0, d0, rep0 = tnm(model, q, K)
R, T, n, d, rep = tnm_ba(model, q, K, R0, T0, n0, d0)
print(f"Reprojection error (BA) = {rep:.3} px")
"""


def _peer_solve(data: str):
    """One peer solve in this process (``tnm`` then ``tnm_ba``): its mean reprojection error (px)."""
    from ast import literal_eval

    from tnm import tnm, tnm_ba

    model = np.loadtxt(os.path.join(data, "model.txt"))
    q = np.array([np.loadtxt(os.path.join(data, f"input{i}.txt")) for i in range(1, 6)])
    K = np.loadtxt(os.path.join(data, "camera.txt"), converters=lambda v: literal_eval(str(v).replace(",", "")))
    start = time.perf_counter()
    R0, T0, n0, d0, _ = tnm(model, q, K)
    rep = tnm_ba(model, q, K, R0, T0, n0, d0)[4]
    return time.perf_counter() - start, float(rep)


def task_peer(case: str, repeats: int) -> dict:
    """``case``: the peer's directory. The same 5 photographs solved by the peer and by ``calibrate()``,
    alternating in this process (imports done first: solve times only)."""
    from mirror_fg import calibrate, load_dataset

    sys.path.insert(0, case)
    data = takahashi_dir()
    dataset = load_dataset(os.path.join(data, "dataset.json"))
    _peer_solve(data), calibrate(dataset)  # warm: imports and first-call costs out of the figures
    peer, ours, stages = [], [], []
    for _ in range(repeats):
        seconds, rep = _peer_solve(data)
        peer.append(seconds)
        start = time.perf_counter()
        cal = calibrate(dataset)
        ours.append(time.perf_counter() - start)
        stages.append(cal.timings)
    rms = float(np.sqrt(np.mean(cal.residual_norms ** 2)))
    mean = float(np.mean(cal.residual_norms))
    return {"peer": float(np.median(peer)), "ours": float(np.median(ours)), "peer_rep_px": rep, "ours_mean_px": mean,
            "ours_rms_px": rms, "consensus": float(np.median([t.get("consensus", 0.0) for t in stages])),
            "load": os.getloadavg()[0]}


def _wall(command, repeats: int, **kwargs) -> tuple[float, subprocess.CompletedProcess]:
    """Median wall time over ``repeats`` runs of ``command`` (a list, or run number -> list: outputs are
    never written over), and the last run."""
    times = []
    for run in range(repeats):
        start = time.perf_counter()
        done = subprocess.run(command(run) if callable(command) else command, capture_output=True, text=True, **kwargs)
        times.append(time.perf_counter() - start)
    return float(np.median(times)), done


def startup_report(peer_source: str | None, repeats: int) -> list[tuple[str, str, bool]]:
    """``--startup``: ``mirror-fg --version``, the start-up of ``calibrate`` on the embedded example (its wall
    time less the ``time`` it prints, which runs from reading the input to the summary), and the peer side by side (in one process and
    as commands) when a checkout of it is given. Prints the figures; returns goal rows."""
    import re
    import tempfile

    cli = [sys.executable, "-m", "mirror_fg"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # as installed: byte code cached (here in a temporary prefix, even where PYTHONDONTWRITEBYTECODE is set)
        env = dict(os.environ, PYTHONPATH=REPO_ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
                   PYTHONPYCACHEPREFIX=os.path.join(tmp, "pycache"))
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        subprocess.run(cli + ["calibrate", EXAMPLE, "-o", os.path.join(tmp, "warm.json")], capture_output=True, env=env)
        print(f"start-up (median of {repeats} runs, byte code cached; load average {os.getloadavg()[0]:.2f})")
        yardstick, _ = _wall([sys.executable, "-c", "import numpy, gtsam"], repeats, env=env)
        print(f"   python -c 'import numpy, gtsam' (yardstick: this machine now) {yardstick:6.3f} s")
        version, _ = _wall(cli + ["--version"], repeats, env=env)
        print(f"   mirror-fg --version                       {version:6.3f} s")
        rows.append((f"mirror-fg --version <= {STARTUP_GOALS['version']:g} s", f"{version:.3f} s",
                     version <= STARTUP_GOALS["version"]))
        wall, done = _wall(lambda run: cli + ["calibrate", "-v", EXAMPLE, "-o", os.path.join(tmp, f"base{run}.json")],
                           repeats, env=env)
        printed = done.stdout + done.stderr
        stages = re.search(r"stage timings: (.*)", printed)
        solve = sum(float(x) for x in re.findall(r" ([0-9.]+) s", stages.group(1))) if stages else float("nan")
        clock = re.search(r"^time ([0-9.]+) s", printed, re.MULTILINE)  # from reading the input to the summary
        work = float(clock.group(1)) if clock else float("nan")
        startup = wall - work
        print(f"   mirror-fg calibrate examples/base_case.json {wall:6.3f} s = start-up {startup:.3f} s (interpreter, "
              f"imports, arguments) + reading, solving, writing {work:.3f} s (of which calibrate() {solve:.3f} s)")
        rows.append((f"calibrate start-up <= {STARTUP_GOALS['calibrate']:g} s", f"{startup:.3f} s",
                     startup <= STARTUP_GOALS["calibrate"]))
        data, peer = takahashi_dir(), peer_checkout(peer_source, tmp)
        if data is None or peer is None:
            why = "the Takahashi data is not found" if data is None else (
                f"no checkout of {PEER} (--peer DIR or $MIRROR_FG_PEER: a checkout or its git directory)")
            print(f"peer comparison skipped: {why}")
            return rows
        same = _run("peer", peer, max(repeats, 3))
        print(f"the same 5 real photographs (Takahashi et al. 2012) beside {PEER} (python/tnm.py; load "
              f"{same['load']:.2f})")
        print(f"   in one process: peer {same['peer']:.3f} s (mean reprojection {same['peer_rep_px']:.3f} px), ours "
              f"{same['ours']:.3f} s (mean {same['ours_mean_px']:.3f} px, rms {same['ours_rms_px']:.3f} px; screening "
              f"{same['consensus']:.3f} s)")
        script = os.path.join(tmp, "peer_demo.py")
        with open(script, "w", encoding="utf-8") as handle:
            handle.write(_PEER_SCRIPT)
        subprocess.run([sys.executable, script, peer, data], capture_output=True, env=env)  # byte code cached
        peer_wall, _ = _wall([sys.executable, script, peer, data], repeats, env=env)
        ours_wall, _ = _wall(lambda run: cli + ["calibrate", os.path.join(data, "dataset.json"), "-o",
                                                os.path.join(tmp, f"takahashi{run}.json")], repeats, env=env)
        print(f"   as commands:    peer {peer_wall:.3f} s, mirror-fg calibrate {ours_wall:.3f} s")
        rows.append(("faster than the peer in one process", f"{same['ours']:.3f} vs {same['peer']:.3f} s",
                     same["ours"] < same["peer"]))
        rows.append(("faster than the peer as a command", f"{ours_wall:.3f} vs {peer_wall:.3f} s", ours_wall < peer_wall))
    return rows


TASKS = {
    "baseline": task_baseline,
    "scaling": task_scaling,
    "fast": lambda case, repeats: task_calibrate(case, repeats, fast=True),
    "reference": lambda case, repeats: task_calibrate(case, repeats, fast=False),
    "linearize": task_linearize,
    "scipy": task_scipy,
    "profile": task_profile,
    "oracle": task_oracle,
    "peer": task_peer,
    "loop": task_loop,
    "rig": task_rig,
}


# --------------------------------------------------------------------------------------------------
# Parent side: run the tasks, print the report.


def _run(task: str, case: str, repeats: int) -> dict:
    command = [sys.executable, os.path.abspath(__file__), "--worker", task, case, str(repeats)]
    done = subprocess.run(command, capture_output=True, text=True)
    for line in done.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise RuntimeError(f"benchmark task {task} on {case} failed:\n{done.stdout}\n{done.stderr}")


def _split(m: dict) -> str:
    """The ``timings`` split, and the rest of the wall time (residuals and outliers after the solve)."""
    parts = ("analytic", "build", "optimize", "marginals")
    other = m["wall"] - sum(m.get(key, 0.0) for key in parts)
    return " + ".join(f"{key} {m.get(key, 0.0):.3f}" for key in parts) + f" + other {other:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs of the fast path and linearisation (median)")
    parser.add_argument("--slow-repeats", type=int, default=3, help="runs of the reference and scipy baselines")
    parser.add_argument("--quick", action="store_true", help="1 repeat each (a smoke test, not figures)")
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    parser.add_argument("--profile", action="store_true", help="pyinstrument profile of one fast calibration")
    parser.add_argument("--native-profile", action="store_true",
                        help="py-spy profile (native frames) of fast calibrations: where the time goes inside GTSAM")
    parser.add_argument("--json", help="also write every figure to this JSON file")
    parser.add_argument("--scaling", action="store_true",
                        help="time per stage and peak memory over 1k, 3k, 10k, 30k, 100k images (fresh process each)")
    parser.add_argument("--scaling-max", type=int, default=SCALING_SIZES[-1], metavar="N",
                        help="--scaling: stop after the sizes <= N images")
    parser.add_argument("--scaling-timeout", type=float, default=300.0, metavar="S",
                        help="--scaling: give up a size (and the larger ones) after S seconds")
    parser.add_argument("--startup", action="store_true",
                        help="only the start-up figures (mirror-fg --version, calibrate) and the peer comparison")
    parser.add_argument("--peer", metavar="DIR",
                        help=f"a checkout (or git directory) of {PEER} for --startup's side-by-side figures")
    parser.add_argument("--rig", action="store_true",
                        help="only the three-camera rig at 480 and 4,800 images beside the tree at 4,800 (goals' ratios)")
    parser.add_argument("--worker", nargs=3, metavar=("TASK", "CASE", "REPEATS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        task, case, repeats = args.worker
        if os.environ.get("MIRROR_FG_BENCH_TREE_FACTORS") == "1":  # the tree solved on its own factors (not the default)
            import reference.lm as reference_lm

            reference_lm.select(tree_factors=True)
        print("RESULT " + json.dumps(TASKS[task](case, int(repeats))))
        return 0
    if args.scaling:
        rows = scaling_table(args.scaling_max, args.scaling_timeout)
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"scaling": rows}, f, indent=1)
        return 0
    repeats, slow = (1, 1) if args.quick else (args.repeats, args.slow_repeats)
    if args.rig:
        rows = rig_table(1)
        print("\nGoals")
        for goal, value, met in rows:
            print(f"   {'met    ' if met else 'NOT met'}  {goal:55s} {value}")
        return 0
    if args.startup:
        rows = startup_report(args.peer, repeats)
        print("\nGoals")
        for goal, value, met in rows:
            print(f"   {'met    ' if met else 'NOT met'}  {goal:55s} {value}")
        return 0

    from importlib.metadata import version

    from mirror_fg.core.transform import rotation_angle

    load_start = os.getloadavg()
    print(f"mirror_fg benchmark  {time.strftime('%Y-%m-%d %H:%M:%S')}  python {sys.version.split()[0]}  "
          f"gtsam {version('gtsam')}  numpy {np.__version__}  scipy {version('scipy')}")
    print(f"cpus {os.cpu_count()}  load average at start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}  "
          f"repeats: fast {repeats}, baselines {slow} (medians)")
    report: dict = {"cases": {}}
    goal_rows = []
    for case in args.cases:
        print(f"\n=== {CASES[case]['title']} ===")
        base = _run("baseline", case, 1)
        fast = _run("fast", case, repeats)
        reference = _run("reference", case, slow)
        linearize = _run("linearize", case, repeats)
        baseline = _run("scipy", case, slow)
        profile = _run("profile", case, 1) if args.profile else None
        native = native_profile(case, max(repeats, 3)) if args.native_profile else None
        oracle = _run("oracle", case, max(min(repeats, 3), 1)) if CASES[case].get("oracle") else None
        report["cases"][case] = {
            "baseline": base, "fast": fast, "reference": reference, "linearize": linearize, "scipy": baseline,
            "profile": profile, "native_profile": native, "oracle": oracle,
        }
        fm, rm, sm = fast["median"], reference["median"], baseline["median"]
        print(f"fast path: {fast['mode']}")
        print("1. calibrate() seconds (median)       total   = analytic + build + optimize (LM) + marginals + other")
        for name, m, runs in [("fast", fm, repeats), ("reference", rm, slow)]:
            print(f"   {name:10s} wall {m['wall']:7.3f}  cpu {m['cpu']:7.3f}  = {_split(m)}   ({runs} runs)")
        print(f"   fast vs reference: {rm['wall'] / fm['wall']:.1f}x overall, "
              f"{(rm['optimize'] + rm['marginals']) / (fm['optimize'] + fm['marginals']):.1f}x on LM + marginals; "
              f"LM iterations {fast['estimate']['iterations']} / {reference['estimate']['iterations']}")
        lin = linearize["results"]
        print(f"2. per measurement, {linearize['measurements']} measurements (medians, CPU time)")
        print(f"   {'':34s} {'factors':>8s} {'linearize':>10s} {'error()':>9s} {'LM iter':>9s}  us/meas")
        labels = {"native": "GTSAM GenericProjectionFactorCal3_S2", "stacked": "one model, stacked",
                  "fast": "one model, placements eliminated", "reference": "reference ViewFactor per image"}
        for name in ("native", "stacked", "fast", "reference"):
            r = lin[name]
            print(f"   {labels[name]:34s} {r['factors']:8d} {r['linearize_us']:10.3f} {r['error_us']:9.3f} {r['lm_iteration_us']:9.3f}")
        ratio = lin["fast"]["linearize_us"] / lin["native"]["linearize_us"]  # what calibrate() linearises
        print(f"   eliminated linearisation = {ratio:.2f}x native floor (its placements solved inside; stacked "
              f"{lin['stacked']['linearize_us'] / lin['native']['linearize_us']:.2f}x); reference = "
              f"{lin['reference']['linearize_us'] / lin['native']['linearize_us']:.0f}x")
        fast_stage = fm["optimize"] + fm["marginals"]
        scipy_stage = sm["optimize"] + sm["marginals"]
        scipy_total = sm["wall"]
        print(f"3. scipy least_squares (trf, sparse structure, 2-point differences) + inv(J^T J), {slow} runs")
        print(f"   wall {scipy_total:7.3f}  cpu {sm['cpu']:7.3f}  = analytic {sm['analytic']:.3f} + build {sm['build']:.3f} + "
              f"solve {sm['optimize']:.3f} ({baseline['nfev']} evaluations) + covariance {sm['marginals']:.3f} "
              f"({baseline['covariance_dim']} unknowns)")
        d_rot = np.degrees(rotation_angle(baseline["estimate"]["R"], fast["estimate"]["R"]))
        d_t = 1000.0 * np.linalg.norm(np.subtract(baseline["estimate"]["t"], fast["estimate"]["t"]))
        print(f"   scipy vs GTSAM estimate: {d_rot:.2e} deg, {d_t:.2e} mm; cost {baseline['final_error']:.6f} vs "
              f"{fast['estimate']['final_error']:.6f}")
        print(f"   fast calibrate() is {scipy_total / fm['wall']:.1f}x faster overall, "
              f"{scipy_stage / fast_stage:.1f}x on solve + covariance")
        print("4. peak memory (ru_maxrss of each task's process), MB")
        print(f"   interpreter + gtsam + data {base['peak_mb']:7.1f}   fast calibrate {fast['peak_mb']:7.1f}   "
              f"reference {reference['peak_mb']:7.1f}   scipy {baseline['peak_mb']:7.1f}   linearisation runs {linearize['peak_mb']:7.1f}")
        if oracle:
            print(f"5. LM stage against a dense numpy LM (dense_lm: grouped forward differences, dense J^T J, "
                  f"{oracle['unknowns']} unknowns), alternating in one process, load {oracle['load']:.2f}")
            print(f"   ours {oracle['optimize']:.3f} s ({oracle['iterations']} iterations), dense {oracle['oracle']:.3f} s "
                  f"({oracle['oracle_iterations']} iterations): {oracle['ratio']:.2f}x; cost {oracle['final_error']:.6f} "
                  f"vs {oracle['oracle_final_error']:.6f}")
        if profile:
            print("profile of one fast calibrate() (pyinstrument):")
            print("\n".join("   " + line for line in profile["text"].splitlines() if line.strip()))
        if native:
            print("where calibrate() spends its time (py-spy --native, share of samples):")
            print("\n".join("   " + line for line in native.splitlines()))
        goal_rows.append((f"{case}: calibrate() <= {GOALS[case]:g} s", f"{fm['wall']:.3f} s", fm["wall"] <= GOALS[case]))
        goal_rows.append((f"{case}: linearisation <= {LINEARISE_GOAL:.0f}x native", f"{ratio:.2f}x", ratio <= LINEARISE_GOAL))
        speedup = scipy_total / fm["wall"]
        goal_rows.append((f"{case}: >= {SPEEDUP_GOAL:.0f}x faster than scipy (total)", f"{speedup:.1f}x", speedup >= SPEEDUP_GOAL))
        stage = scipy_stage / fast_stage
        goal_rows.append((f"{case}: >= {SPEEDUP_GOAL:.0f}x faster than scipy (solve + covariance)", f"{stage:.1f}x", stage >= SPEEDUP_GOAL))
        if oracle:
            goal_rows.append((f"{case}: LM stage <= {ORACLE_GOAL:g}x dense numpy LM", f"{oracle['ratio']:.2f}x",
                              oracle["ratio"] <= ORACLE_GOAL))
        if case == "900img":
            goal_rows.append((f"{case}: peak memory <= {MEMORY_GOAL_MB:.0f} MB", f"{fast['peak_mb']:.0f} MB", fast["peak_mb"] <= MEMORY_GOAL_MB))
    load_end = os.getloadavg()
    print(f"\nload average at end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f} on {os.cpu_count()} cpus "
          "(wall >> cpu above means other processes took the cores)")
    print("\nGoals")
    for goal, value, met in goal_rows:
        print(f"   {'met    ' if met else 'NOT met'}  {goal:55s} {value}")
    report["goals"] = [{"goal": g, "value": v, "met": bool(m)} for g, v, m in goal_rows]
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
