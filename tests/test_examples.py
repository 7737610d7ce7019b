"""The examples a new user runs work from a clone: the real photographs ship in examples/takahashi2012
(with their BSD-3 licence), and no README, docs or test capture points outside the repository."""
import re
from pathlib import Path

import pytest

from conftest import REPO
from mirror_fg.cli import main
from mirror_fg.io.capture import load_capture
from mirror_fg.io.dataset import load_dataset

REAL = REPO / "examples" / "takahashi2012"
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")), *sorted((REPO / "tests" / "data" / "capture").rglob("*.yaml"))]


def test_real_photographs_ship_with_their_licence():
    for n in range(1, 6):
        assert (REAL / f"input{n}.jpg").stat().st_size > 10_000
        assert (REAL / f"input{n}.txt").exists()
    assert "Redistribution and use in source and binary forms" in (REAL / "LICENSE.txt").read_text()
    assert (REAL / "model.txt").exists() and (REAL / "camera.txt").exists()


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(REPO)))
def test_no_example_points_outside_the_repository(document):
    assert "shared/data" not in document.read_text()


@pytest.mark.parametrize("document", DOCUMENTS[:1] + [d for d in DOCUMENTS if d.suffix == ".md"][1:],
                         ids=lambda p: str(p.relative_to(REPO)))
def test_every_example_path_in_the_docs_exists(document):
    """Each ``examples/...`` path in a shell or YAML block is a file of the repository."""
    text = document.read_text()
    for block in re.findall(r"```(?:bash|yaml)\n(.*?)```", text, flags=re.S):
        for path in re.findall(r"(?:\.\./)*examples/[\w./-]+\.\w+", block):
            base = REPO if not path.startswith("..") else REPO / "tests" / "data" / "capture"
            assert (base / path).resolve().exists(), f"{document.name}: {path}"


def test_the_real_capture_finds_its_photographs():
    capture = load_capture(REPO / "tests" / "data" / "capture" / "takahashi.yaml")
    files = [Path(image.file) for image in capture.images]
    assert len(files) == 5 and all(f.exists() and f.resolve().parent == REAL.resolve() for f in files)


@pytest.mark.parametrize("name, fiducials", [("dataset.json", 70), ("dataset_3p.json", 3)])
def test_the_shipped_datasets_calibrate_from_the_clone(name, fiducials, tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the README's commands run from the repository's root
    assert len(load_dataset(Path("examples/takahashi2012") / name).fiducials) == fiducials
    assert main(["calibrate", f"examples/takahashi2012/{name}", "-o", str(tmp_path / "r.json")]) == 0


def test_the_tag_grid_template_is_a_valid_capture_and_plans(capsys):
    """examples/capture_tag_grid.yaml validates (before its photographs exist), its T_base_target is the
    stated one (rows along base +y, up +z, out +x), and ``plan --capture`` takes it."""
    import numpy as np

    from mirror_fg.io.capture import capture_from_file_data
    from mirror_fg.io.fileio import load_structured

    template = REPO / "examples" / "capture_tag_grid.yaml"
    capture = capture_from_file_data(load_structured(template), str(template), media=False)
    assert np.allclose(capture.R_base_target.T, [[0, 1, 0], [0, 0, 1], [1, 0, 0]])  # rows: the grid's axes in base
    grid = capture.target.target_points()
    spacing = np.linalg.norm(grid["T1_0"] - grid["T0_0"])
    assert spacing == pytest.approx(0.060 * (1 + 0.3))  # Kalibr tagSpacing 0.3 as the comment says
    assert main(["plan", "--capture", str(template), "--placements", "3", "--images", "12", "--draws", "1"]) == 0
    assert "48 target points (apriltag)" in capsys.readouterr().out


def test_capture_guide_quotes_the_real_example_as_it_calibrates():
    """docs/capture_guide.md's figures for the shipped photographs are what calibrating them gives, and
    it does not call their analytic vs MLE distance (a good result) a bad sign."""
    import math

    import numpy as np

    import mirror_fg
    from mirror_fg.core.transform import rotation_angle

    guide = " ".join((REPO / "docs" / "capture_guide.md").read_text().split())
    result = mirror_fg.calibrate(load_dataset(REAL / "dataset.json")).to_dict()
    rms = result["residuals"]["rms_px"]
    assert f"RMS {rms:.3f} px = {rms / (math.sqrt(2) * 0.5):.2f} × √2·σ" in guide
    sigma3 = result["sigma3_cam_base"]
    assert "±[" + ", ".join(f"{x:.3f}" for x in sigma3["rotation_deg"]) + "] deg" in guide
    assert "±[" + ", ".join(f"{x:.2f}" for x in sigma3["position_mm"]) + "] mm" in guide
    R, t = np.array(result["T_cam_base"]["R"]), np.array(result["T_cam_base"]["t"])
    Ra, ta = np.array(result["analytic"]["T_cam_base"]["R"]), np.array(result["analytic"]["T_cam_base"]["t"])
    apart = f"{1000 * np.linalg.norm(ta - t):.1f} mm and {math.degrees(rotation_angle(Ra, R)):.2f}° apart"
    assert apart in guide
    assert "Analytic and optimised poses far apart" not in guide
