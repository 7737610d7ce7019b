"""``calibrate --at`` / ``--validate`` on the command line, their console lines, and the report's section
(report/units.py): the points, the map of the largest 3-sigma over the image, the validation."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mirror_fg.cli import main
from mirror_fg.core.transform import Transform
from mirror_fg.io.dataset import dataset_to_dict, load_dataset
from mirror_fg.io.result import load_result
from mirror_fg.solver.result.point_error import point_error
from mirror_fg.report.units import MAP_DEPTHS_M, largest_sigma3_map, units_blocks
from mirror_fg.simulate.tree import simulate_base_case


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("units")
    dataset, _ = simulate_base_case(num_images=40, seed=9)
    path = folder / "ds.json"
    path.write_text(json.dumps(dataset_to_dict(dataset)))
    return folder, path


def test_calibrate_at_and_validate_write_and_print(calibrated, capsys):
    folder, path = calibrated
    out = folder / "r.json"
    assert main(["calibrate", str(path), "-o", str(out), "--no-ros", "--at", "0,0,0.6", "--at", "0.1,-0.1,2",
                 "--validate"]) == 0
    printed = capsys.readouterr().out
    result = load_result(out)
    assert [e["point_cam"] for e in result["at"]] == [[0.0, 0.0, 0.6], [0.1, -0.1, 2.0]]
    R, t = np.array(result["T_base_cam"]["R"]), np.array(result["T_base_cam"]["t"])
    expected = point_error(Transform(R, t), np.array(result["covariance_base_cam"]), [0.1, -0.1, 2.0])
    np.testing.assert_allclose(result["at"][1]["sigma3_mm"], expected.sigma3_mm, rtol=1e-9)
    validation = result["validation"]
    assert validation["images"] == 40 and 0.5 < validation["ratio"] < 1.5
    assert validation["worst"]["image"].startswith("img")
    lines = printed.splitlines()
    bounds = next(i for i, line in enumerate(lines) if "3-sigma bounds in base axes" in line)
    at = next(i for i, line in enumerate(lines) if line.startswith("at p_cam [0.000, 0.000, 0.600] m"))
    assert at > bounds and "mm along base x, y, z" in lines[at]
    assert any(line.startswith("held-out validation over 40 image(s): ratio") for line in lines)


@pytest.mark.parametrize("text", ["0,0", "a,b,c", "0,0,inf", "1,2,3,4"])
def test_a_bad_point_is_one_line_and_exit_2(calibrated, capsys, text):
    folder, path = calibrated
    with pytest.raises(SystemExit) as stop:
        main(["calibrate", str(path), "-o", str(folder / "bad.json"), "--at", text])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--at" in err[0] and "X,Y,Z" in err[0]
    assert not (folder / "bad.json").exists()


def test_the_map_is_the_point_error_at_each_pixel():
    """A pixel's value is point_error's worst direction at depth z along its ray, and grows with depth for a
    pose whose rotation is uncertain."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(6, 6)) * 1e-3
    P = A @ A.T
    T = Transform(np.eye(3), np.array([0.1, 0.0, 0.2]))
    normalized = np.array([[0.0, 0.0], [0.3, -0.2]])
    for z in MAP_DEPTHS_M:
        got = largest_sigma3_map(T, P, normalized, z)
        for k, (x, y) in enumerate(normalized):
            assert got[k] == pytest.approx(point_error(T, P, [z * x, z * y, z]).largest_sigma3_mm, rel=1e-12)
    assert largest_sigma3_map(T, P, normalized, 2.0)[1] > largest_sigma3_map(T, P, normalized, 0.5)[1]


def test_report_section_with_and_without_the_dataset(calibrated):
    folder, path = calibrated
    out = folder / "r2.json"
    assert main(["calibrate", str(path), "-o", str(out), "--no-ros", "-q", "--at", "0,0,0.6"]) == 0
    result, dataset = load_result(out), load_dataset(path)
    blocks = units_blocks(result, dataset)
    ids = {b.id for b in blocks}
    assert {"point-error", "validation"} <= ids
    figures = [b for b in blocks if b.kind == "figure"]
    assert len(figures) == 2 and "0.5, 1 and 2 m" in figures[0].text and "Held-out" in figures[1].text
    alone = units_blocks(result, None)  # no dataset, no validation in the result: the map only, and a note
    assert [b.kind for b in alone].count("figure") == 1
    assert any("no held-out validation" in b.text for b in alone)


def test_the_readme_example_runs_and_prints_what_it_shows(tmp_path):
    """docs/reports.md's "How far off will my grasp be?" command, run as written (from the repository root, the
    output moved to a temporary folder): the lines it shows come out, figures and all."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    section = (repo / "docs" / "reports.md").read_text().split("## How far off will my grasp be?", 1)[1].split("\n#", 1)[0]
    command = re.search(r"```bash\n(.*?)\n```", section, re.S).group(1)
    shown = re.search(r"```text\n(.*?)\n```", section, re.S).group(1).splitlines()
    command = command.replace("mirror-fg ", f"{sys.executable} -m mirror_fg ").replace("out/", f"{tmp_path}/")
    run = subprocess.run(command, shell=True, cwd=repo, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(repo), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    for line in shown:
        assert line in run.stdout.splitlines()


@pytest.mark.parametrize("edit, words", [
    (lambda r: r["at"][0].update(point_cam=[0, 1]), "at[0].point_cam: expected 3 numbers"),
    (lambda r: r["at"][0].update(covariance=[[1, 0, 0]]), "at[0].covariance: expected 3 rows"),
    (lambda r: r["validation"].update(ratio="x"), "validation.ratio"),
    (lambda r: r["validation"].update(worst={"image": ""}), "validation.worst.image"),
])
def test_a_malformed_at_or_validation_is_refused_by_name(calibrated, edit, words):
    """A result file's ``at`` and ``validation`` are checked like its other keys (one line naming the key)."""
    from mirror_fg.core.errors import DatasetError
    from mirror_fg.io.result import validate_result

    folder, path = calibrated
    out = folder / "r3.json"
    if not out.exists():
        assert main(["calibrate", str(path), "-o", str(out), "--no-ros", "-q", "--at", "0,0,0.6", "--validate"]) == 0
    result = load_result(out)
    assert validate_result(result, "r3.json") == result
    edit(result)
    with pytest.raises(DatasetError, match=words.replace("[", r"\[").replace("]", r"\]")):
        validate_result(result, "r3.json")
