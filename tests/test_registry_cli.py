"""``--registry URL --robot ID`` on the commands and ``mirror-fg history``: the result file is always written
first; a database that is down, read-only, full or newer costs no file and ends the run with exit 2 and one
line saying the record was not stored."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from registry_docs import result_document, verification_document
from sqlalchemy import text

from conftest import load_script
from mirror_fg.cli import main
from mirror_fg.registry import Registry

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("data") / "bench.json"
    assert main(["simulate", "-o", str(path), "--images", "30", "-q"]) == 0
    return path


def run_cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    environment = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    environment.pop("MIRROR_FG_REGISTRY", None)
    environment.update(env or {})
    return subprocess.run([sys.executable, "-m", "mirror_fg", *args], capture_output=True, text=True, timeout=300,
                          env=environment)


def test_calibrate_records_the_written_result(dataset, tmp_path):
    url = f"sqlite:///{tmp_path / 'r.db'}"
    out = tmp_path / "result.json"
    done = run_cli("calibrate", str(dataset), "-o", str(out), "--no-ros", "--registry", url, "--robot", "arm-7")
    assert done.returncode == 0, done.stderr
    assert "recorded in" in done.stdout and "robot arm-7, calibration of camera" in done.stdout
    with Registry(url) as registry:
        [record] = registry.history("arm-7")
        latest = registry.latest("arm-7")
    written = json.loads(out.read_text())
    assert latest.document == written and record.kind == "calibration" and record.verdict == "looks right"
    assert record.input_sha256 == hashlib.sha256(dataset.read_bytes()).hexdigest()
    assert record.t_m == pytest.approx(tuple(written["T_base_cam"]["t"]))
    assert record.sigma3_position_mm == pytest.approx(tuple(written["sigma3_base_cam"]["position_mm"]))
    # the environment gives the URL; --robot says to record
    again = run_cli("calibrate", str(dataset), "-o", str(tmp_path / "second.json"), "--no-ros", "--robot", "arm-7",
                    env={"MIRROR_FG_REGISTRY": url})
    assert again.returncode == 0, again.stderr
    with Registry(url) as registry:
        assert len(registry.history("arm-7")) == 2


@pytest.mark.parametrize("args,words", [
    (["--registry", "sqlite:///x.db"], "--registry needs --robot"),
    (["--robot", "arm"], "--robot needs a registry"),
    (["--robot", "arm", "--registry", "mysql://u@h/db"], "SQLite"),
])
def test_registry_options_are_checked_before_the_work(dataset, tmp_path, args, words):
    out = tmp_path / "result.json"
    done = run_cli("calibrate", str(dataset), "-o", str(out), "--no-ros", *args)
    assert done.returncode == 2 and words in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    assert not out.exists()


def _unusable(kind: str, tmp_path: Path) -> str:
    """A registry URL that cannot take a record, for ``kind``."""
    path = tmp_path / f"{kind}.db"
    if kind == "down":
        return "postgresql://postgres@127.0.0.1:1/registry"  # nothing listens on port 1
    with Registry(f"sqlite:///{path}") as registry:
        registry.record("arm", result_document())
        if kind == "newer":
            with registry.engine.begin() as connection:
                connection.execute(text("UPDATE alembic_version SET version_num = 'ffff'"))
    return f"sqlite:///file:{path}?mode=ro&uri=true" if kind == "read-only" else f"sqlite:///{path}"


@pytest.mark.parametrize("kind,words", [("down", "connect"), ("read-only", "readonly"), ("newer", "newer")])
def test_a_database_that_cannot_record_costs_no_result_file(dataset, tmp_path, kind, words):
    out = tmp_path / "result.json"
    done = run_cli("calibrate", str(dataset), "-o", str(out), "--no-ros", "--registry", _unusable(kind, tmp_path),
                   "--robot", "arm")
    assert done.returncode == 2, done.stderr
    [line] = done.stderr.splitlines()
    # the error line keeps a long path's start and end (cli/printing.py): its last 30 characters at least
    assert "the record was not stored" in line and words in line.lower() and f"{str(out)[-30:]} is written" in line, line
    assert json.loads(out.read_text())["format"] == "mirror-fg/result@1"


def test_a_full_database_costs_no_result_file(dataset, tmp_path, capsys):
    """In this process: every connection's database may grow by no page (SQLite's max_page_count)."""
    import sqlite3

    from sqlalchemy import Engine, event

    url = _unusable("full", tmp_path)
    pages = sqlite3.connect(url.removeprefix("sqlite:///")).execute("PRAGMA page_count").fetchone()[0]

    def no_room(connection, _record) -> None:
        if isinstance(connection, sqlite3.Connection):
            connection.execute(f"PRAGMA max_page_count={pages}")

    out = tmp_path / "result.json"
    event.listen(Engine, "connect", no_room)
    try:
        status = main(["calibrate", str(dataset), "-o", str(out), "--no-ros", "-q", "--registry", url, "--robot", "arm"])
    finally:
        event.remove(Engine, "connect", no_room)
    [line] = capsys.readouterr().err.splitlines()
    assert status == 2 and "not stored" in line and "full" in line, line
    assert json.loads(out.read_text())["format"] == "mirror-fg/result@1"


def test_calibrate_many_says_which_records_were_not_stored(dataset, tmp_path):
    out = tmp_path / "out"
    done = run_cli("calibrate-many", str(dataset), "-o", str(out), "--registry", _unusable("read-only", tmp_path))
    assert done.returncode == 2 and "1 of 1 record(s) not stored" in done.stderr, done.stderr
    assert (out / "bench.result.json").exists()


def test_live_records_its_result(tmp_path):
    render = load_script("render_live")
    session = render.session(640, 480, placements=5, hold=3, move=2, seed=3)
    render.write_video(session, tmp_path / "session.avi")
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(render.capture_dict(session.camera), sort_keys=False))
    url = f"sqlite:///{tmp_path / 'r.db'}"
    done = run_cli("live", str(tmp_path / "capture.yaml"), "--source", str(tmp_path / "session.avi"), "-o",
                   str(tmp_path / "live.json"), "--no-ros", "--registry", url, "--robot", "bench")
    assert done.returncode == 0, done.stderr
    with Registry(url) as registry:
        assert registry.latest("bench").document == json.loads((tmp_path / "live.json").read_text())


def test_history_prints_plots_and_tables(tmp_path, capsys, monkeypatch):
    from datetime import datetime, timedelta, timezone

    monkeypatch.delenv("MIRROR_FG_REGISTRY", raising=False)
    url = f"sqlite:///{tmp_path / 'h.db'}"
    t0 = datetime(2026, 3, 1, tzinfo=timezone.utc)
    with Registry(url) as registry:
        for day, x in enumerate([100.0, 101.0, 100.5, 112.0, 112.5]):
            rig = {"left": ((x, 0.0, 50.0), (0.0, 0.0, 0.1 * day)), "right": ((160.0, 0.0, 50.0), (0.0, 0.0, 5.0))}
            registry.record("arm", result_document(cameras=rig), time=t0 + timedelta(days=7 * day))
        registry.record("arm", verification_document({"left": "moved", "right": "not moved"}),
                        time=t0 + timedelta(days=25))
    assert main(["history", "arm", "--registry", url]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert [line.split(":")[1].strip() for line in printed if line.startswith("CHANGED")] == ["left between run 3 (2026-03-15 00"]
    html, table = tmp_path / "history.html", tmp_path / "history.csv"
    assert main(["history", "arm", "--registry", url, "-o", str(html), "-q"]) == 0
    page = html.read_text()
    assert page.count("<img") == 2 and "1 change(s) beyond the combined 3-sigma" in page
    monkeypatch.setenv("MIRROR_FG_REGISTRY", url)  # the URL from the environment
    assert main(["history", "arm", "--camera", "right", "-o", str(table), "-q"]) == 0
    assert len(table.read_text().splitlines()) == 1 + 6
    monkeypatch.delenv("MIRROR_FG_REGISTRY")
    capsys.readouterr()
    for args, words in ((["nobody"], "robots there: arm"), (["arm", "-o", str(tmp_path / "h.pdf")], ".html"),
                        (["arm"], "needs a registry")):
        status = main(["history", *args, *(["--registry", url] if words != "needs a registry" else [])])
        err = capsys.readouterr().err
        assert status == 2 and words in err and len(err.splitlines()) == 1, err


def test_readme_registry_commands_run(tmp_path):
    """The README's registry example, verbatim: two calibrations recorded, their history written."""
    import re

    readme = (REPO / "README.md").read_text()
    section = readme.split("### Registry:", 1)[1].split("\n## ", 1)[0]
    [commands] = re.findall(r"```bash\n(.*?)\n```", section, flags=re.S)
    mirror_fg = f"{sys.executable} -c 'import sys; from mirror_fg.cli import main; sys.exit(main())'"
    environment = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run(commands.replace("mirror-fg ", f"{mirror_fg} "), shell=True, cwd=tmp_path, env=environment,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "<img" in (tmp_path / "history.html").read_text()
    with Registry(f"sqlite:///{tmp_path / 'registry.db'}") as registry:
        assert len(registry.history("arm-1")) == 2


def test_verify_records_its_verification(tmp_path):
    """``verify --registry URL --robot ID`` records the verification@1 (kind verification, the verdict) after
    its files, under the camera name the calibration was recorded under."""
    url = f"sqlite:///{tmp_path / 'r.db'}"
    stored, today = tmp_path / "stored.json", tmp_path / "today.json"
    assert main(["simulate", "--mirrors", "1", "--images", "30", "--fiducials", "4", "--sigma", "0.1", "--seed", "1",
                 "-o", str(stored), "-q"]) == 0
    assert main(["simulate", "--mirrors", "1", "--images", "6", "--fiducials", "4", "--sigma", "0.1", "--seed", "2",
                 "-o", str(today), "-q"]) == 0
    result = tmp_path / "stored.result.json"
    done = run_cli("calibrate", str(stored), "-o", str(result), "--no-ros", "--registry", url, "--robot", "cell-3")
    assert done.returncode == 0, done.stderr
    out = tmp_path / "verification.json"
    checked = run_cli("verify", str(result), str(today), "-o", str(out), "--tolerance-mm", "10", "--tolerance-deg", "1",
                      "--registry", url, "--robot", "cell-3")
    assert checked.returncode in (0, 5), checked.stderr
    with Registry(url) as registry:
        calibration, verification = registry.history("cell-3")
    written = json.loads(out.read_text())
    assert (calibration.kind, verification.kind) == ("calibration", "verification")
    assert verification.camera == calibration.camera
    assert verification.verdict == written["cameras"][verification.camera]["verdict"]
    # no URL, no robot: nothing is recorded and nothing is asked
    assert run_cli("verify", str(result), str(today), "--tolerance-mm", "10", "--tolerance-deg", "1").returncode in (0, 5)
