"""Shared fixtures: paths to the real data shipped in the repository (examples/takahashi2012); loading a script as a module."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
TAKAHASHI = REPO / "examples" / "takahashi2012"


def load_script(name: str):
    """``scripts/<name>.py`` as a module, registered under ``name`` (worker processes unpickle by it)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def takahashi_dir() -> Path:
    if not (TAKAHASHI / "dataset.json").exists():
        pytest.skip(f"real data not found at {TAKAHASHI}")
    return TAKAHASHI


def pose_difference(R_ref, t_ref, R, t) -> np.ndarray:
    """docs/formats.md-convention difference ``[dtheta, dt]`` taking (R_ref, t_ref) to (R, t): R = Exp(dtheta) R_ref."""
    D = np.asarray(R) @ np.asarray(R_ref).T
    angle = np.arccos(np.clip((np.trace(D) - 1) / 2, -1, 1))
    axis = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    dtheta = axis * (0.5 if angle < 1e-8 else angle / (2 * np.sin(angle)))
    return np.r_[dtheta, np.asarray(t) - np.asarray(t_ref)]


@pytest.fixture(scope="session")
def postgres_cluster(request):
    """A throwaway PostgreSQL server (tests/postgres_cluster.py) for the whole session; skipped, saying why on the
    terminal, where the server binaries are missing or it cannot start (.ci/run installs Debian's postgresql)."""
    from postgres_cluster import PostgresCluster, find_binaries

    def skip(reason: str) -> None:
        terminal = request.config.pluginmanager.get_plugin("terminalreporter")
        capture = request.config.pluginmanager.get_plugin("capturemanager")
        if terminal is not None and capture is not None:  # past the capture: CI's log shows these tests did not run
            with capture.global_and_fixture_disabled():
                terminal.write_line(f"SKIPPED the PostgreSQL registry tests: {reason}", yellow=True, bold=True)
        pytest.skip(reason)

    bindir = find_binaries()
    if bindir is None:
        skip("no PostgreSQL server binaries (initdb, pg_ctl): apt-get install postgresql")
    cluster = PostgresCluster(bindir)
    try:
        cluster.start()
    except Exception as error:  # noqa: BLE001 - any reason it cannot start is a skip with that reason
        cluster.stop()
        skip(f"the PostgreSQL server did not start: {error}")
    yield cluster
    cluster.stop()
