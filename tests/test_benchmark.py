"""scripts/benchmark.py: the native-profile breakdown puts each sample where it belongs."""
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def benchmark():
    return load_script("benchmark")


def test_native_breakdown_splits_calibrate_samples(benchmark):
    top = "<module> (x.py:1);calibrate (mirror_fg/graph.py:455)"
    lm = "gtsam::NonlinearOptimizer::optimize (libgtsam.so);gtsam::LevenbergMarquardtOptimizer::iterate (libgtsam.so)"
    subtree = "initial_estimate (g.py:1);solve_analytic (a.py:1);_refine_subtree (mirror_fg/graph.py:414)"
    raw = "\n".join([
        f"{top};solve_analytic (a.py:3);_choose_candidates (a.py:9) 30",
        f"{top};{subtree};{lm};gtsam::CustomFactor::unwhitenedError (libgtsam.so) 10",
        f"{top};{lm};gtsam::JacobianFactor::updateHessian (libgtsam.so) 20",
        f"{top};{lm};gtsam::EliminateCholesky (libgtsam.so);gtsam::eliminate (libgtsam.so) 15",
        f"{top};{lm};gtsam::Values::Values (libgtsam.so) 5",
        f"{top};marginal_covariances (mirror_fg/graph.py:300) 10",
        f"{top};build_graph (mirror_fg/graph.py:99) 5",
        f"{top};residual_statistics (mirror_fg/graph.py:250) 5",
        "<module> (x.py:1);simulate_base_case (s.py:1) 400",  # outside calibrate(): not counted
    ])
    shares = dict(benchmark.native_breakdown(raw))
    assert shares == pytest.approx({
        "initial estimate: PnP and closed form (numpy, OpenCV)": 0.30,
        "initial estimate: subtree LM: our Python factors (error and Jacobians)": 0.10,
        "main LM: GTSAM forms the Hessian of each dense factor": 0.20,
        "main LM: GTSAM Cholesky elimination (the rest)": 0.15,
        "main LM: GTSAM other (Values, damping, error sums)": 0.05,
        "marginals (Schur complement, GTSAM Marginals)": 0.10,
        "graph building (factors, initial values)": 0.05,
        "residual statistics and the rest (Python)": 0.05,
    })
    assert benchmark.native_breakdown("") == []


def test_scaling_task_reports_stages_and_memory(benchmark):
    row = benchmark.task_scaling("60", 1)
    assert row["images"] == 60 and row["converged"]
    for key in ("analytic", "optimize", "marginals", "wall", "peak_mb"):
        assert row[key] > 0


def test_dense_lm_oracle_reaches_the_mle(benchmark):
    """The oracle the LM stage is timed against solves the same problem: calibrate()'s final cost."""
    from mirror_fg import calibrate, initial_estimate
    from mirror_fg.simulate.tree import simulate_base_case

    dataset, _ = simulate_base_case(num_images=24, num_points=4, seed=3)
    initial = initial_estimate(dataset)
    residuals, sparsity, x0, _ = benchmark._scipy_problem(dataset, initial)
    groups = benchmark._column_groups(sparsity)
    pattern = sparsity.toarray().astype(bool)
    for group in groups:  # the columns of a group share no row: one evaluation differences them all
        assert pattern[:, group].sum(axis=1).max() <= 1
    assert sorted(int(c) for g in groups for c in g) == list(range(len(x0)))
    _, _, cost = benchmark.dense_lm(residuals, sparsity, x0)
    assert cost == pytest.approx(calibrate(dataset, initial=initial).final_error, rel=1e-7)


def test_the_peer_comes_from_a_checkout_or_a_git_directory_or_not_at_all(benchmark, tmp_path, monkeypatch):
    import subprocess

    monkeypatch.delenv("MIRROR_FG_PEER", raising=False)
    repo = tmp_path / "peer"
    (repo / "python").mkdir(parents=True)
    (repo / "python" / "tnm.py").write_text("VALUE = 1\n")
    into = tmp_path / "into"
    into.mkdir()
    assert benchmark.peer_checkout(None, str(into)) is None  # nothing given: the comparison is skipped
    assert benchmark.peer_checkout(str(repo), str(into)) == str(into)
    assert (into / "tnm.py").read_text() == "VALUE = 1\n"
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git + ["init", "-q"], check=True)
    subprocess.run(git + ["add", "python/tnm.py"], check=True)
    subprocess.run(git + ["commit", "-q", "-m", "peer"], check=True)
    (into / "tnm.py").unlink()
    assert benchmark.peer_checkout(str(repo / ".git"), str(into)) == str(into)
    assert (into / "tnm.py").read_text() == "VALUE = 1\n"
    assert benchmark.peer_checkout(str(tmp_path / "missing"), str(into)) is None
