"""Monte Carlo checks of the MLE (scripts/reproduce_fig4.py, scripts/convergence.py): efficiency against the
Cramér-Rao bound, consistency of the reported covariance, NEES, convergence from the analytical guess.

Sampling error: an RMS over N runs estimates a standard deviation to about 1/sqrt(2N) (7 % at N = 100,
22 % at N = 10), so a per-axis ratio "MLE RMS / CRB 1-sigma" is compared with its chi-square band. The
efficiency itself is measured without that error against the first-order estimator
``x_true + I^-1 J^T Sigma^-1 (z - h(x_true))`` on the *same* noise, which is efficient by construction,
and that estimator (whose covariance is the bound exactly) is the control variate of an estimate of the
MLE's mean squared error that holds the issue's 10 % thresholds.
"""
from __future__ import annotations

import numpy as np
import pytest
from conftest import load_script

from mirror_fg.solver.information.crb import chi2_quantile

_script = load_script


def _sampling_band(num_runs: int, comparisons: int, alpha: float = 0.01) -> tuple[float, float]:
    """Two-sided band of ``RMS / sigma`` over ``num_runs`` Gaussian runs, Bonferroni over ``comparisons``."""
    a = alpha / comparisons / 2
    return (float(np.sqrt(chi2_quantile(a, num_runs) / num_runs)),
            float(np.sqrt(chi2_quantile(1 - a, num_runs) / num_runs)))


def _check_statistics(stats: dict, runs: int, comparisons: int) -> None:
    """The MLE checks over ``runs`` runs at the global optimum."""
    assert stats["runs_global"] == runs
    # Efficiency, sampling error removed: the MLE is no worse than the efficient first-order estimator.
    assert np.all(stats["efficiency_first_order"] <= 1.10), stats["efficiency_first_order"]
    # The thresholds on the MLE's RMS error estimated with that estimator as control variate
    # (unbiased, sampling noise mostly cancelled): RMS / CRB <= 1.10 and reported 1-sigma within 10 %.
    assert np.all(stats["efficiency_cv"] <= 1.10), stats["efficiency_cv"]
    assert np.all(np.abs(stats["consistency_cv"] - 1.0) <= 0.10), stats["consistency_cv"]
    assert np.all(stats["point_mle_rms_global"] / stats["point_first_order_rms"] <= 1.10)
    # The reported covariance is the bound (evaluated at the estimate instead of the truth).
    np.testing.assert_allclose(stats["reported_sigma_global"] / stats["crb_sigma_global"], 1.0, atol=0.10)
    np.testing.assert_allclose(stats["point_reported_sigma_global"] / stats["point_crb_sigma_global"], 1.0, atol=0.10)
    # Efficiency and consistency as raw ratios: inside the sampling band of `runs` runs.
    lo, hi = _sampling_band(runs, comparisons)
    assert np.all(stats["efficiency"] <= hi), (stats["efficiency"], hi)
    assert np.all((lo <= 1 / stats["consistency"]) & (1 / stats["consistency"] <= hi)), (stats["consistency"], lo, hi)
    # NEES of the 6-DoF pose with the reported covariance, inside the 95 % band of the mean.
    band = stats["nees_band"]
    assert band[0] < stats["nees_reported"] < band[1], (stats["nees_reported"], band)


def test_small_monte_carlo_is_efficient_and_consistent():
    fig4 = _script("reproduce_fig4")
    runs = 10
    points = [("a", 0.5, 0.5)]
    records = fig4.run_sweep(points, runs, num_images=60, num_points=10, jobs=1, progress=False)
    stats = fig4.summarize(records)
    assert stats["runs_ok"] == runs and stats["runs_singular"] == 0 and stats["converged_fraction"] == 1.0
    assert stats["runs_local_minimum"] == 0, stats["local_minimum_seeds"]  # every LM reached the global optimum
    _check_statistics(stats, runs, comparisons=6)
    # The analytical solution is worse than the MLE but within the paper's range (<= ~4 cm, ~4 deg at 2 px).
    assert np.all(stats["analytic_rms"] >= stats["mle_rms"])
    rot_deg, pos_m = fig4.worst_axis(stats["analytic_rms"])
    assert rot_deg < 5.0 and pos_m < 0.10
    rows = fig4.csv_rows(records, points)
    assert rows[0]["runs_ok"] == runs
    assert rows[0]["mle_rms_pos_worst_m"] == pytest.approx(np.max(stats["mle_rms"][3:]))
    assert rows[0]["crb_sigma_rot_worst_deg"] == pytest.approx(np.degrees(np.max(stats["crb_sigma"][:3])))


@pytest.fixture(scope="module")
def base_case_runs(tmp_path_factory):
    """Reduced Fig. 4 run: the full base case (200 images, 60 points) at 0.5 and 2 px, 30 runs each."""
    fig4 = _script("reproduce_fig4")
    points = [("a", 0.5, 0.5), ("a", 2.0, 0.5)]
    out = tmp_path_factory.mktemp("fig4")
    records = fig4.run_sweep(points, 30, num_images=200, num_points=60, jobs=2, log_path=out / "runs.jsonl",
                             progress=False)
    return fig4, points, records, out


@pytest.mark.slow
def test_base_case_monte_carlo_is_efficient_and_consistent(base_case_runs):
    """Efficiency and consistency of the MLE over the runs whose LM reached the global optimum."""
    fig4, points, records, out = base_case_runs
    for _, sigma, _ in points:
        stats = fig4.summarize([r for r in records if r["sigma_px"] == sigma])
        assert stats["runs_global"] >= 0.9 * stats["runs_ok"]
        _check_statistics(stats, stats["runs_global"], comparisons=6 * len(points))
    rows = fig4.csv_rows(records, points)
    fig4.write_csv(out / "fig4.csv", rows)
    fig4.plot(rows, out / "fig4.png", "test")
    assert (out / "fig4.png").stat().st_size > 10_000


@pytest.mark.slow
def test_lm_from_the_analytical_guess_reaches_the_global_optimum(base_case_runs):
    fig4, points, records, _ = base_case_runs
    for _, sigma, _ in points:
        stats = fig4.summarize([r for r in records if r["sigma_px"] == sigma])
        assert stats["runs_local_minimum"] == 0, (sigma, stats["local_minimum_seeds"])


def test_sweep_resumes_from_its_log(tmp_path):
    fig4 = _script("reproduce_fig4")
    log = tmp_path / "runs.jsonl"
    points = [("a", 0.5, 0.5)]
    first = fig4.run_sweep(points, 1, num_images=9, num_points=2, jobs=1, log_path=log, progress=False)
    again = fig4.run_sweep(points, 2, num_images=9, num_points=2, jobs=1, log_path=log, progress=False)
    assert len(first) == 1 and len(again) == 2
    assert len(log.read_text().splitlines()) == 2
    assert again[0]["mle_pose"] == first[0]["mle_pose"]


def test_convergence_from_the_analytical_guess():
    conv = _script("convergence")
    record = conv.run_trial(seed=0, num_images=30, num_points=3, max_iterations=30)
    assert not record["analytic"]["singular"]
    assert conv.succeeded(record["analytic"], 30) and record["analytic"]["iterations"] <= 10
    assert record["naive"]["iterations"] >= 1
    summary = conv.summarize([record])
    assert summary["analytic_success_rate"] == 1.0 and summary["runs"] == 1


def test_naive_guess_knows_nothing():
    conv = _script("convergence")
    from mirror_fg.simulate.tree import simulate_base_case

    dataset, _ = simulate_base_case(num_images=9, num_points=2, pixel_sigma=0.0, seed=0)
    guess = conv.naive_guess(dataset)
    np.testing.assert_array_equal(guess.R_cam_base, np.eye(3))
    assert {tuple(v) for (l, _), v in guess.mirror_vectors.items() if l == 2} == {(0.0, 0.0, 0.5)}  # in front
    assert {tuple(v) for (l, _), v in guess.mirror_vectors.items() if l == 1} == {(0.0, 0.0, -0.5)}  # behind
    centroid = np.mean(list(dataset.fiducials.values()), axis=0)
    for p in guess.points.values():
        np.testing.assert_allclose(p, centroid)


def test_control_variate_detects_an_inefficient_estimator():
    """Synthetic runs: an 'MLE' 30 % worse than the first-order estimator on the same noise fails the
    control-variate efficiency check (1.10), and an efficient one reads 1.0 to 2 % at 50 runs."""
    fig4 = _script("reproduce_fig4")
    rng = np.random.default_rng(1)
    sigmas = np.array([1e-3, 2e-3, 1e-3, 0.01, 0.01, 0.02])

    def records(gain: float) -> list[dict]:
        out = []
        for seed in range(50):
            scale = rng.uniform(0.5, 2.0)  # geometries differ between runs
            cov = np.diag((scale * sigmas) ** 2)
            first_order = rng.normal(scale=scale * sigmas)
            mle = gain * first_order + rng.normal(scale=1e-3 * scale * sigmas)
            out.append({"status": "ok", "seed": seed, "mle_pose": mle.tolist(), "first_order_pose": first_order.tolist(),
                        "crb_cov": cov.tolist(), "reported_cov": cov.tolist(), "analytic_pose": (2 * mle).tolist(),
                        "closed_form_pose": (3 * mle).tolist(), "iterations": 4, "converged": True, "seconds": 1.0})
        return out

    inefficient = fig4.summarize(records(1.3))  # far from the control variate: its noise is back (~0.69 x 10 %)
    assert np.all(inefficient["efficiency_cv"] > 1.15) and np.all(inefficient["consistency_cv"] < 0.87)
    efficient = fig4.summarize(records(1.0))
    np.testing.assert_allclose(efficient["efficiency_cv"], 1.0, rtol=0.02)
    np.testing.assert_allclose(efficient["consistency_cv"], 1.0, rtol=0.02)


def test_a_script_trial_runs_on_a_local_dask_cluster_without_hanging():
    """A trial function from a script loaded by path is not importable in the Dask workers: before, each
    worker died unpickling it and was restarted forever (the slow Fig. 4 test hung). Its code now
    travels by value."""
    import signal

    def too_long(signum, frame):
        raise TimeoutError("run_trials on a local Dask cluster did not finish in 120 s")

    fig4 = _script("reproduce_fig4")
    previous = signal.signal(signal.SIGALRM, too_long)
    signal.alarm(120)
    try:
        records = fig4.run_sweep([("a", 1.0, 0.5)], 2, num_images=30, num_points=0, jobs=2, progress=False)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert len(records) == 2 and all(r["status"] == "ok" and r["converged"] for r in records)
