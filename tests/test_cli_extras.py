"""Small command-line promises: --version, python -m mirror_fg, -v stage timings."""
import json
import subprocess
import sys

import mirror_fg
from mirror_fg.cli import main
from mirror_fg.io.dataset import dataset_to_dict
from mirror_fg.simulate.tree import simulate_base_case


def test_version_from_the_command_and_the_package(capsys):
    try:
        main(["--version"])
    except SystemExit as stop:
        assert stop.code == 0
    assert capsys.readouterr().out.strip() == f"mirror-fg {mirror_fg.__version__}"
    assert mirror_fg.__version__ and mirror_fg.__version__[0].isdigit()


def test_python_dash_m_runs_the_command():
    proc = subprocess.run([sys.executable, "-m", "mirror_fg", "--version"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.startswith("mirror-fg ")


def test_verbose_prints_stage_timings(tmp_path, capsys):
    dataset, _ = simulate_base_case(num_images=30, seed=2)
    path = tmp_path / "d.json"
    path.write_text(json.dumps(dataset_to_dict(dataset)))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "-v"]) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if l.startswith("stage timings:"))
    for stage in ("analytic", "optimize", "marginals"):
        assert stage in line


def test_report_takes_the_capture_the_result_came_from(tmp_path, capsys):
    from pathlib import Path

    capture = Path(__file__).parent / "data" / "capture" / "rendered" / "capture.yaml"
    assert main(["calibrate", str(capture), "-o", str(tmp_path / "r.json"), "-q"]) == 0
    assert main(["report", str(tmp_path / "r.json"), str(capture), "-o", str(tmp_path / "rep"), "-q"]) == 0
    html = (tmp_path / "rep" / "report.html").read_text()
    assert "capture.yaml" in html and (tmp_path / "rep" / "report.pdf").stat().st_size > 0


def test_calibrate_many_lists_the_failure_and_calibrates_the_rest(tmp_path, capsys):
    dataset, _ = simulate_base_case(num_images=30, seed=4)
    good = tmp_path / "robot1.json"
    good.write_text(json.dumps(dataset_to_dict(dataset)))
    bad = tmp_path / "robot2.json"
    bad.write_text('{"format": "mirror-fg/dataset@1", "num_mirrors": 2}')
    code = main(["calibrate-many", str(good), str(bad), "-o", str(tmp_path / "out"), "--workers", "2", "-q"])
    assert code == 2
    assert "1 of 2 input(s) failed" in capsys.readouterr().err
    result = json.loads((tmp_path / "out" / "robot1.result.json").read_text())
    assert result["format"] == "mirror-fg/result@1" and not (tmp_path / "out" / "robot2.result.json").exists()
