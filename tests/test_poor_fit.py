"""Wrong answers that passed as success: a fit the noise model cannot explain, two photographs
labelled as one placement, sizes in millimetres where metres are meant. ``require_converged`` refuses them
for ``mirror-fg calibrate``, ``calibrate-many`` and ``--incremental`` alike, unless accepted."""
import json
import re
from dataclasses import replace

import numpy as np
import pytest

from mirror_fg import calibrate
from mirror_fg.cli import main
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import dataset_to_dict, load_dataset
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import POOR_FIT_RATIO, require_converged
from mirror_fg.simulate.tree import simulate_base_case


@pytest.fixture
def mislabelled(takahashi_dir, tmp_path):
    """The real photographs with input3 given input2's placement (``mirror_configs: [1]``)."""
    data = json.loads((takahashi_dir / "dataset.json").read_text())
    assert [im["id"] for im in data["images"][1:3]] == ["input2", "input3"]
    data["images"][2]["mirror_configs"] = [1]
    path = tmp_path / "mislabelled.json"
    path.write_text(json.dumps(data))
    return path


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def test_mislabelled_placement_exits_3_naming_the_images(mislabelled, takahashi_dir, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(["calibrate", str(mislabelled), "-o", str(out)]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "input2 and input3 are labelled placement 1 of mirror 1 but their mirrors differ by" in err
    assert "the result was not written" in err and "--accept-poor-fit" in err
    assert not out.exists() and not (tmp_path / "r.ros.yaml").exists() and not (tmp_path / "r.urdf.xml").exists()
    # The figures are those of the two photographs' own mirrors, correctly labelled (an independent
    # calibration); each image's mirror is fitted at the mislabelled solve's pose, biased by the wrong
    # label, hence the tolerance of a degree and a centimetre.
    degrees, mm = map(float, re.search(r"differ by ([\d.]+)° / (\d+) mm", err).groups())
    right = calibrate(load_dataset(takahashi_dir / "dataset.json"))
    v2, v3 = right.mirror_vectors[(1, 1)], right.mirror_vectors[(1, 2)]
    assert degrees == pytest.approx(_angle_deg(v2, v3), abs=1.0)
    assert mm == pytest.approx(1000 * abs(np.linalg.norm(v2) - np.linalg.norm(v3)), abs=10.0)


def test_mislabelled_placement_in_the_api(mislabelled):
    calibration = calibrate(load_dataset(mislabelled))
    assert calibration.converged and calibration.fit_ratio > POOR_FIT_RATIO
    assert calibration.inconsistency is not None and calibration.inconsistency.groups == (("input2",), ("input3",))
    with pytest.raises(SolveError, match="input2 and input3 are labelled placement 1"):
        require_converged(calibration, "mislabelled")
    assert require_converged(calibration, "mislabelled", accept_poor_fit=True) is calibration


def test_accept_poor_fit_writes_the_result_with_its_inconsistency(mislabelled, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(["calibrate", str(mislabelled), "-o", str(out), "--accept-poor-fit"]) == 0
    result = json.loads(out.read_text())
    assert result["inconsistency"]["groups"] == [["input2"], ["input3"]]
    assert "labelled placement 1 of mirror 1" in capsys.readouterr().out  # the summary's warning


def test_calibrate_many_marks_the_mislabelled_row_failed(mislabelled, takahashi_dir, tmp_path):
    from mirror_fg.analysis.many import calibrate_one

    bad = calibrate_one(str(mislabelled), str(tmp_path / "out"), ros=False)
    assert bad["status"] == "failed" and "input2 and input3 are labelled placement 1" in bad["reason"]
    assert not (tmp_path / "out" / "mislabelled.result.json").exists()
    assert calibrate_one(str(takahashi_dir / "dataset.json"), str(tmp_path / "out"), ros=False)["status"] == "ok"


def test_real_photographs_keep_exit_0(takahashi_dir, tmp_path):
    """Their unmodelled distortion puts the cost about 1.3x above its expected value: a warning's worth
    (the report's verdict), not a refusal."""
    calibration = calibrate(load_dataset(takahashi_dir / "dataset.json"))
    assert 1.0 < calibration.final_error / calibration.expected_final_error < 2.0
    assert main(["calibrate", str(takahashi_dir / "dataset.json"), "-o", str(tmp_path / "r.json"), "-q"]) == 0


def _declared_sigma(true_sigma: float, declared: float, seed: int = 5) -> Dataset:
    noisy, _ = simulate_base_case(num_images=45, pixel_sigma=true_sigma, seed=seed)
    return replace(noisy, pixel_sigma=declared, source=f"<{true_sigma} px declared {declared} px>")


def test_a_sigma_far_too_small_exits_3_with_the_likely_causes(tmp_path, capsys):
    dataset = _declared_sigma(1.0, 0.25)
    calibration = calibrate(dataset)
    # fit_ratio estimates the true over the declared sigma (an independent figure: 4).
    assert calibration.fit_ratio == pytest.approx(4.0, rel=0.15)
    path = tmp_path / "d.json"
    path.write_text(json.dumps(dataset_to_dict(dataset)))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    for cause in ("mirror_configs labels", "pixel_sigma", "distortion", "a camera that moved"):
        assert cause in err
    assert not (tmp_path / "r.json").exists()


def test_a_sigma_twice_too_small_still_passes():
    """A ratio of 2 is within what a plausible sigma explains (the rule: more than 3x)."""
    calibration = calibrate(_declared_sigma(1.0, 0.5))
    assert not calibration.cost_plausible and calibration.fit_ratio == pytest.approx(2.0, rel=0.15)
    assert require_converged(calibration, "<sigma x2>") is calibration


def test_incremental_judges_its_final_cost():
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

    dataset = _declared_sigma(1.0, 0.25)
    with pytest.raises(SolveError, match="times worse than the noise model allows"):
        calibrate_incremental(dataset)
    calibration = calibrate_incremental(dataset, accept_poor_fit=True)
    batch = calibrate(dataset)
    assert calibration.expected_final_error == batch.expected_final_error
    assert calibration.fit_ratio == pytest.approx(batch.fit_ratio, rel=1e-3)


def test_base_tens_of_metres_away_is_refused_naming_the_unit():
    """Fiducials in millimetres in a metres field: the scene scaled by 1000 projects the same, so the MLE
    is the one in metres scaled by 1000 (the base some 70 m away)."""
    dataset, _ = simulate_base_case(num_images=45, pixel_sigma=0.5, seed=5)
    millimetres = replace(dataset, fiducials={name: 1000.0 * p for name, p in dataset.fiducials.items()},
                          source="<millimetres>")
    try:
        calibration = calibrate(millimetres)
    except DatasetError as error:  # refused at input (the target's size) before the solve: also right
        assert "metre" in str(error)
        return
    metres = calibrate(dataset)
    assert calibration.t_cam_base == pytest.approx(1000 * metres.t_cam_base, rel=1e-3)
    with pytest.raises(DatasetError, match=r"T_cam_base puts the base [\d.]+ m from the camera: are the target's "
                                           r"sizes in metres"):
        require_converged(calibration, "<millimetres>", accept_poor_fit=True)
    assert require_converged(metres, "<metres>") is metres
