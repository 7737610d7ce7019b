"""calibrate-many under faults (analysis/many.py, analysis/montecarlo.py): schedulers that are not there or are not
Dask, a worker killed while the local cluster starts, an input whose worker keeps dying; and small jobs run in
this process, with the same rows as on Dask.

Workers are killed deterministically by worker preload modules (``distributed.worker.preload``): one whose
``calibrate_one`` calls ``os._exit`` for an input named ``crash*``, one whose worker exits while it starts.
"""
from __future__ import annotations

import http.server
import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import dask
import dask.distributed  # its config section exists before any dask.config.set below
import numpy as np
import pytest
from conftest import REPO

from mirror_fg import cli
from mirror_fg.io.dataset import dataset_text
from mirror_fg.analysis.many import calibrate_many, runs_in_process
from mirror_fg.simulate.tree import simulate_base_case

CRASH_ON_INPUT = '''
import os
import mirror_fg.analysis.many as many

_calibrate_one = getattr(many, "_unpatched_calibrate_one", many.calibrate_one)  # preloads may run twice
many._unpatched_calibrate_one = _calibrate_one


def calibrate_one(path, out_dir, **kwargs):
    if os.path.basename(path).startswith("crash"):
        os._exit(1)  # as the OOM killer would
    return _calibrate_one(path, out_dir, **kwargs)


many.calibrate_one = calibrate_one  # what a task naming mirror_fg.analysis.many.calibrate_one runs here
'''

DIE_AT_START = '''
import os

MARKER = {marker!r}


def dask_setup(worker):
    if MARKER:  # only the first worker to start dies
        try:
            os.close(os.open(MARKER, os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            return
    os._exit(1)
'''


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("inputs")
    paths = {}
    for seed in (1, 2):
        dataset, _ = simulate_base_case(num_images=24, seed=seed)
        paths[f"robot{seed}"] = folder / f"robot{seed}.json"
        paths[f"robot{seed}"].write_text(dataset_text(dataset))
    paths["broken"] = folder / "broken.json"
    paths["broken"].write_text('{"format": "mirror-fg/dataset@1", "num_mirrors": 2}')
    paths["crash"] = folder / "crash.json"  # a good dataset whose worker dies (the preload kills it)
    paths["crash"].write_text(paths["robot1"].read_text())
    return paths


#: Worker deaths a task survives (Dask's default is 3; fewer restarts keep the test fast).
ALLOWED_FAILURES = 1


@pytest.fixture(scope="module")
def scheduler():
    """One local cluster shared by the tests that compare with Dask."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        yield cluster.scheduler_address


def _cli(*args) -> int:
    return cli.main([str(a) for a in args])


# --- schedulers that are not there --------------------------------------------------------------------------

@pytest.mark.parametrize("address, words", [
    ("not-an-address", "unknown host"),
    ("tcp://127.0.0.1:99999", "the port must be a number from 1 to 65535"),
    ("http://127.0.0.1:8786", "unsupported scheme 'http'"),
])
def test_a_malformed_scheduler_address_is_one_line(address, words, inputs, tmp_path, capsys):
    assert _cli("calibrate-many", inputs["robot1"], "-o", tmp_path / "out", "--scheduler", address) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("mirror-fg: error: scheduler ") and address in err
    assert words in err


def test_a_refusing_scheduler_port_is_one_line_at_once(inputs, tmp_path, capsys):
    with socket.socket() as unused:  # a port nothing listens on
        unused.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{unused.getsockname()[1]}"
    assert _cli("calibrate-many", inputs["robot1"], "-o", tmp_path / "out", "--scheduler", address) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"mirror-fg: error: scheduler {address}: cannot connect (Connection refused)"
    assert not (tmp_path / "out").exists()  # nothing left behind


def test_a_port_answering_with_an_http_error_is_not_a_scheduler(inputs, tmp_path, capsys):
    with socket.create_server(("127.0.0.1", 0)) as server:
        def answer() -> None:
            connection, _ = server.accept()
            with connection:
                connection.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
        threading.Thread(target=answer, daemon=True).start()
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        status = _cli("calibrate-many", inputs["robot1"], "-o", tmp_path / "out", "--scheduler", address)
    assert status == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"scheduler {address}: the server there is not a Dask scheduler" in err


def test_an_http_server_port_times_out_with_one_line(inputs, tmp_path):
    """An HTTP server waits for a request, as distributed waits for a handshake: today that hangs for ever (run
    in a subprocess so that it fails rather than hangs); the probe gives up after --connect-timeout."""
    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    address = f"tcp://127.0.0.1:{server.server_address[1]}"
    try:
        done = subprocess.run([sys.executable, "-m", "mirror_fg", "calibrate-many", str(inputs["robot1"]), "-o",
                               str(tmp_path / "out"), "--scheduler", address, "--connect-timeout", "1"],
                              env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60, check=False)
    finally:
        server.shutdown()
        server.server_close()
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == (f"mirror-fg: error: scheduler {address}: no Dask scheduler answered within 1 s "
                                   "(a firewall, or another kind of server on that port?; --connect-timeout SECONDS)")


# --- workers that die ---------------------------------------------------------------------------------------

#: What a command run as a user runs it inherits from this test process: nothing else (not what earlier tests
#: or this process's imports put in its environment, e.g. Dask or OpenCV settings).
_USER_ENVIRONMENT = ("PATH", "HOME", "USER", "LANG", "LC_ALL", "TMPDIR", "TZ")


def clean_environment(**settings: str) -> dict[str, str]:
    """A user's environment for a command run as a subprocess: the basics, the repository, ``settings``."""
    env = {name: os.environ[name] for name in _USER_ENVIRONMENT if name in os.environ}
    return {**env, "PYTHONPATH": str(REPO), **settings}


def test_an_input_whose_worker_keeps_dying_is_a_failed_row(inputs, tmp_path):
    """The command as a user runs it (a subprocess: distributed's own log lines would reach its stderr), on a
    local cluster whose workers die on the ``crash`` input until Dask gives that input up."""
    preload = tmp_path / "crash_on_input.py"
    preload.write_text(CRASH_ON_INPUT)
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "mirror_fg", "calibrate-many", *map(str, (
        inputs["robot1"], inputs["crash"], inputs["robot2"])), "-o", str(out), "--dask"],
        env=clean_environment(DASK_DISTRIBUTED__WORKER__PRELOAD=json.dumps([str(preload)]),
                              DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=str(ALLOWED_FAILURES)),
        cwd=tmp_path, start_new_session=True, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 2, done.stderr
    deaths = ALLOWED_FAILURES + 1  # then Dask gives the task up
    assert "2 of 3 calibrated" in done.stdout
    crash_row = next(line for line in done.stdout.splitlines() if "crash.json" in line)
    assert "FAILED" in crash_row and f"its worker died {deaths} times (out of memory?)" in crash_row
    assert done.stderr.strip() == "mirror-fg: error: 1 of 3 input(s) failed (listed above)"
    assert sorted(p.name for p in out.glob("*.result.json")) == ["robot1.result.json", "robot2.result.json"]


def _die_at_start(folder: Path, first_only: bool) -> dict:
    preload = folder / "die_at_start.py"
    preload.write_text(DIE_AT_START.format(marker=os.fspath(folder / "died") if first_only else ""))
    return {"distributed.worker.preload": [os.fspath(preload)]}


def test_a_worker_killed_while_the_cluster_starts_the_start_is_retried(inputs, tmp_path):
    with dask.config.set(_die_at_start(tmp_path, first_only=True)):
        with pytest.warns(RuntimeWarning, match=r"did not start at the first try \(RuntimeError: Nanny failed to "
                          r"start\); it did at try 2"):
            rows = calibrate_many([inputs["robot1"], inputs["robot2"]], tmp_path / "out", progress=False,
                                  in_process=False)
    assert (tmp_path / "died").exists()  # a worker did die
    assert [row["status"] for row in rows] == ["ok", "ok"]


def test_a_cluster_that_never_starts_falls_back_to_this_process_with_one_line(inputs, tmp_path, capsys):
    with dask.config.set(_die_at_start(tmp_path, first_only=False)):
        status = _cli("calibrate-many", inputs["robot1"], inputs["broken"], "-o", tmp_path / "out", "--dask")
    captured = capsys.readouterr()
    assert status == 2  # the broken input
    assert "1 of 2 calibrated" in captured.out
    assert captured.err.strip().splitlines() == [
        "mirror-fg: warning: the local Dask cluster of 2 worker(s) did not start in 2 tries (RuntimeError: Nanny "
        "failed to start): running in this process instead",
        "mirror-fg: error: 1 of 2 input(s) failed (listed above)",
    ]


# --- small jobs in this process -------------------------------------------------------------------------------

def test_a_small_job_starts_no_cluster(inputs, tmp_path, monkeypatch):
    def no_cluster(*args, **kwargs):
        raise AssertionError("a small job started a Dask cluster")

    monkeypatch.setattr(dask.distributed, "LocalCluster", no_cluster)
    rows = calibrate_many([inputs["robot1"], inputs["broken"], inputs["robot2"]], tmp_path / "out", progress=False)
    assert [row["status"] for row in rows] == ["ok", "failed", "ok"]


def test_the_size_rule_keeps_dask_for_big_jobs(tmp_path):
    small, big = tmp_path / "small.json", tmp_path / "big.json"
    small.write_bytes(b" " * 100_000)
    big.write_bytes(b" " * 4_000_000)  # about 3.3 s of calibration by the measured rate
    assert runs_in_process([small] * 3, workers=2)
    assert not runs_in_process([big], workers=2)
    assert not runs_in_process([small] * 30, workers=2)  # 30 inputs, ~0.18 s each
    assert runs_in_process([big], workers=1)


def test_rows_and_files_are_the_same_in_process_and_on_dask(scheduler, inputs, tmp_path):
    order = [inputs["robot1"], inputs["broken"], inputs["robot2"]]
    here = calibrate_many(order, tmp_path / "here", progress=False)
    there = calibrate_many(order, tmp_path / "there", progress=False, scheduler=scheduler)
    assert [r["status"] for r in here] == [r["status"] for r in there] == ["ok", "failed", "ok"]
    for a, b in zip(here, there):
        assert set(a) == set(b) and a["input"] == b["input"] and a["reason"] == b["reason"]
        if a["status"] == "ok":
            assert Path(a["result"]).name == Path(b["result"]).name
            np.testing.assert_allclose(a["t_cam_base"], b["t_cam_base"], rtol=1e-9)
            files_here = sorted(p.name for p in Path(a["result"]).parent.glob(Path(a["input"]).stem + ".*"))
            files_there = sorted(p.name for p in Path(b["result"]).parent.glob(Path(b["input"]).stem + ".*"))
            assert files_here == files_there
            assert json.loads(Path(a["result"]).read_text())["format"] == "mirror-fg/result@1"
