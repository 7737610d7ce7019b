"""mirror_fg.io.result.validate_result: a corrupt result@1 fails with one line naming the key.

Every key path of a real result is replaced, in turn, by each of a few wrong values; the validator
either refuses it with a short line naming that path, or (optional keys, NaN statistics, extras)
accepts it, and then the readers (report, ROS outputs) raise nothing but DatasetError.
"""
from __future__ import annotations

import copy
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import mirror_fg
from mirror_fg.cli import main
from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.solver.result.calibration import EstimatedCamera, Exclusion, Inconsistency
from mirror_fg.io.dataset import dataset_to_dict
from mirror_fg.report.writer import _summary, write_report
from mirror_fg.report.residuals import compute_residuals
from mirror_fg.io.result import validate_result
from mirror_fg.io.ros import ros_outputs, write_ros_outputs
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.core.transform import rotation_to_quaternion_xyzw

SOURCE = "r.json"
#: A message quotes at most ~80 characters of user data; the whole line stays short.
MAX_MESSAGE = 200


@pytest.fixture(scope="module")
def calibrated() -> tuple[Any, dict[str, Any]]:
    """The simulated base case (30 images, 2 points) and its result@1, once per module, with every optional
    block a result may hold filled in: ``excluded``, ``inconsistency``, ``camera`` (values made up here;
    the validator checks their shape, not where they came from)."""
    ds, _ = simulate_base_case(num_images=30, num_points=2, seed=1)
    calibration = mirror_fg.calibrate(ds)
    ids = [image.id for image in ds.images]
    calibration.excluded = [Exclusion(ids[3], "PnP reprojection 14.2 px (board order wrong?)"),
                            Exclusion(ids[5], "above the final check", point="F1", sigmas=9.5)]
    calibration.inconsistency = Inconsistency((tuple(ids[:4]), tuple(ids[4:])), 3.1, 40.0, "images disagree")
    camera = Camera(model="pinhole", width=800, height=600, fx=801.0, fy=799.0, cx=401.0, cy=298.0,
                    dist=(-0.2, 0.05, 0.0, 0.0, 0.0))
    calibration.camera = EstimatedCamera(camera, ("fx", "fy", "k1"), np.diag([4.0, 4.0, 1e-4]),
                                         np.full((3, 6), 1e-6))
    return ds, calibration.to_dict()


# --------------------------------------------------------------------------------------------------
# Systematic fuzz


def _key_paths(value: Any, keys: tuple = ()) -> Iterator[tuple]:
    """Every key path below ``value`` (dict keys and list indices), parents before children."""
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        yield (*keys, key)
        yield from _key_paths(child, (*keys, key))


def _spelled(keys: tuple) -> str:
    """``mirrors[3].v``: the key path as messages spell it."""
    text = ""
    for key in keys:
        text += f"[{key}]" if isinstance(key, int) else (f".{key}" if text else key)
    return text


def _wrong_length(value: Any) -> Any:
    return value + value[:1] if isinstance(value, list) and value else [1.0, 2.0]


WRONG = {
    "string": lambda v: "abc",
    "null": lambda v: None,
    "wrong_length": _wrong_length,
    "nested": lambda v: {"x": [{"y": [1, "z"]}]},
    "nan": lambda v: math.nan,
    "huge": lambda v: 10**400,
}
_ANY = r"[^.\[]+"  # one key of a point
#: What a result may hold instead of the value, by kind of wrong value (full-match patterns of paths).
ACCEPTED = {
    "all": [],  # optimizer.expected_final_error and residuals.mean_px are read now (summary, report): checked
    "null": [  # optional keys: null means absent
        r"T_base_cam", r"(T_cam_base|T_base_cam|analytic\.T_cam_base)\.q_xyzw", r"analytic(\.T_cam_base)?",
        r"covariance_cam_base", r"sigma3_cam_base(\.\w+)?", r"covariance_base_cam(_ros)?", r"sigma3_base_cam(\.\w+)?",
        r"mirrors", r"mirrors\[\d+\]\.(sigma3_mm|covariance|cross_covariance_cam_base)",
        r"points", rf"points\.{_ANY}\.sigma3_mm", r"optimizer(\.\w+)?", r"residuals(\.\w+)?",
        r"excluded", r"excluded\[\d+\]\.(point|sigmas)", r"inconsistency", r"inconsistency\.(rotation_deg|position_mm)",
        r"camera", r"camera\.(model|width|height|dist|sigma3|covariance|cross_covariance_cam_base)",
        r"camera\.sigma3\.\w+", r"dispersion(\.factor)?",
    ],
    "nan": [  # statistics that could not be computed
        r"sigma3_(cam_base|base_cam)\.\w+\[\d\]", r"mirrors\[\d+\]\.sigma3_mm\[\d\]", rf"points\.{_ANY}\.sigma3_mm\[\d\]",
        r"optimizer\.(initial|final|expected_final)_error", r"residuals\.(rms|max|mean)_px",
        r"excluded\[\d+\]\.sigmas", r"inconsistency\.(rotation_deg|position_mm)", r"camera\.sigma3\.\w+",
    ],
    "wrong_length": [r"excluded", r"inconsistency\.groups(\[\d+\])?", r"camera\.dist"],  # lists of any length
    "string": [r"residuals\.units", r"excluded\[\d+\]\.(image|point|reason)", r"inconsistency\.groups\[\d+\]\[\d+\]",
               r"inconsistency\.message", r"camera\.model"],
    "nested": [r"sigma3_(cam_base|base_cam)", r"analytic", r"optimizer", r"residuals"],  # objects of optional keys only
}


def _acceptable(path: str, kind: str) -> bool:
    return any(re.fullmatch(p, path) for p in ACCEPTED["all"] + ACCEPTED.get(kind, []))


def _assert_one_line(error: DatasetError, *words: str) -> None:
    text = str(error)
    assert "\n" not in text and len(text) < MAX_MESSAGE, text
    for word in words:
        assert word in text, (word, text)


def _readers(result: dict[str, Any], ds: Any, tmp_path: Path) -> None:
    """Everything that reads a result, short of rendering figures: only DatasetError may come out."""
    for read in (
        lambda: validate_result(result, SOURCE),
        lambda: _summary(validate_result(result, SOURCE), ds, compute_residuals(result, ds, source=SOURCE), "base"),
        lambda: _summary(validate_result(result, SOURCE), None, None, "base"),
        lambda: ros_outputs(result),
        lambda: write_ros_outputs(result, tmp_path / SOURCE),
    ):
        try:
            read()
        except DatasetError:
            pass


@pytest.mark.parametrize("kind", list(WRONG))
def test_every_key_path_corrupted(calibrated, kind, tmp_path):
    ds, good = calibrated
    result = copy.deepcopy(good)
    problems: list[str] = []
    accepted = 0
    for keys in list(_key_paths(result)):
        parent = result
        for key in keys[:-1]:
            parent = parent[key]
        original = parent[keys[-1]]
        parent[keys[-1]] = WRONG[kind](copy.deepcopy(original))
        path = _spelled(keys)
        try:
            validate_result(result, SOURCE)
        except DatasetError as error:
            text = str(error)
            if not (text.startswith(f"{SOURCE}: ") and path in text and "\n" not in text and len(text) < MAX_MESSAGE):
                problems.append(f"{path}: bad message {text!r}")
            with pytest.raises(DatasetError):
                write_report(result, ds, tmp_path / "never", progress=False, source=SOURCE)
            with pytest.raises(DatasetError):
                ros_outputs(result)
        else:
            accepted += 1
            if not _acceptable(path, kind):
                problems.append(f"{path}: {kind} accepted")
            _readers(result, ds, tmp_path)
        parent[keys[-1]] = original
    assert not problems, "\n".join(problems[:20])
    assert not (tmp_path / "never").exists()  # refused before any work
    assert result == good
    if kind in ("null", "nan"):
        assert accepted > 0


def test_good_result_is_returned_unchanged_and_plain(calibrated):
    _, good = calibrated
    checked = validate_result(good, SOURCE)
    assert checked == good and checked is not good
    assert validate_result(checked, SOURCE) == checked  # idempotent
    as_numpy = copy.deepcopy(good)
    as_numpy["T_cam_base"]["R"] = np.array(good["T_cam_base"]["R"])
    as_numpy["covariance_cam_base"] = np.array(good["covariance_cam_base"])
    as_numpy["mirrors"][0]["mirror"] = np.int64(1)
    as_numpy["mirrors"][0]["v"] = tuple(np.float32(x) for x in good["mirrors"][0]["v"])
    as_numpy["optimizer"]["converged"] = np.bool_(True)
    plain = validate_result(as_numpy, SOURCE)
    json.dumps(plain)  # JSON-like again
    assert type(plain["mirrors"][0]["mirror"]) is int and plain["optimizer"]["converged"] is True


def test_extra_keys_are_kept(calibrated):
    _, good = calibrated
    result = copy.deepcopy(good)
    result["notes"] = {"fx": 800.0, "anything": [1, "x", None]}
    result["mirrors"][0]["note"] = "kept"
    result["T_cam_base"]["rpy"] = "not read"
    checked = validate_result(result, SOURCE)
    assert checked["notes"] == result["notes"] and checked["mirrors"][0]["note"] == "kept"
    assert checked["T_cam_base"]["rpy"] == "not read"


def _transform(R: np.ndarray, t: np.ndarray) -> dict[str, Any]:
    return {"R": R.tolist(), "t": list(t), "q_xyzw": rotation_to_quaternion_xyzw(R).tolist()}


def _minimal(R: np.ndarray | None = None) -> dict[str, Any]:
    R = np.eye(3) if R is None else R
    return {"format": "mirror-fg/result@1", "T_cam_base": _transform(R, np.array([0.1, 0.2, 0.3]))}


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda r: r.pop("T_cam_base"), ["T_cam_base", "missing"]),
        (lambda r: r.pop("format"), ["missing 'format'"]),
        (lambda r: r.update(format="mirror-fg/dataset@1"), ["unknown format"]),
        (lambda r: r["T_cam_base"].update(R=(1.001 * np.eye(3)).tolist()), ["T_cam_base.R", "not a rotation"]),
        (lambda r: r["T_cam_base"].update(R=np.diag([1.0, 1.0, -1.0]).tolist()), ["T_cam_base.R", "not a rotation"]),
        (lambda r: r["T_cam_base"].update(q_xyzw=[1.0, 0.0, 0.0, 0.0]), ["T_cam_base.q_xyzw", "not the rotation"]),
        (lambda r: r["T_cam_base"].update(q_xyzw=[0.0, 0.0, 0.0, 2.0]), ["T_cam_base.q_xyzw", "unit"]),
        (lambda r: r.update(T_base_cam=_transform(np.eye(3), np.zeros(3))), ["T_base_cam", "not the inverse"]),
        (lambda r: r.update(covariance_cam_base=(np.eye(6) + np.triu(np.ones((6, 6)), 1)).tolist()),
         ["covariance_cam_base", "not symmetric"]),
        (lambda r: r.update(covariance_cam_base=(-np.eye(6)).tolist()), ["covariance_cam_base", "negative variance"]),
        (lambda r: r.update(mirrors=[{"mirror": 1, "config": 0, "v": [0, 0, 0.5]}] * 2), ["mirrors[1]", "again"]),
        (lambda r: r.update(mirrors=[{"mirror": 1, "config": 0, "v": [0, 0, 0]}]), ["mirrors[0].v", "zero"]),
        (lambda r: r.update(mirrors=[{"mirror": 0, "config": 0, "v": [0, 0, 1]}]), ["mirrors[0].mirror"]),
        (lambda r: r.update(mirrors=[{"mirror": 1, "config": -1, "v": [0, 0, 1]}]), ["mirrors[0].config"]),
        (lambda r: r.update(mirrors=[{"mirror": 1.0, "config": 0, "v": [0, 0, 1]}]), ["mirrors[0].mirror", "integer"]),
        (lambda r: r.update(mirrors=[{"mirror": True, "config": 0, "v": [0, 0, 1]}]), ["mirrors[0].mirror", "integer"]),
        (lambda r: r.update(points={"odd name": {"xyz": [1, 2]}}), ["points['odd name'].xyz", "expected 3 numbers"]),
        (lambda r: r.update(points={"": {"xyz": [1, 2, 3]}}), ["points['']", "non-empty string"]),
        (lambda r: r.update(optimizer={"converged": "yes"}), ["optimizer.converged", "true or false"]),
        (lambda r: r.update(optimizer={"iterations": -1}), ["optimizer.iterations"]),
        (lambda r: r.update(residuals={"outliers": [{"image": "i", "point": "P"}]}), ["outliers[0].sigmas", "missing"]),
        (lambda r: r.update(sigma3_cam_base={"rotation_deg": [1, 2, -3]}), ["sigma3_cam_base.rotation_deg[2]"]),
        (lambda r: r.update(residuals=[1, 2]), ["residuals", "expected an object"]),
        (lambda r: r.update(T_cam_base={**r["T_cam_base"], "t": [0.0, "1", 2.0]}), ["T_cam_base.t[1]", "'1'"]),
        (lambda r: r.update(T_cam_base={**r["T_cam_base"], "t": [0.0, math.inf, 2.0]}), ["T_cam_base.t[1]", "finite"]),
    ],
)
def test_specific_problems_are_named(edit, words):
    result = _minimal()
    edit(result)
    with pytest.raises(DatasetError) as exc:
        validate_result(result, SOURCE)
    _assert_one_line(exc.value, SOURCE, *words)


def test_rotation_within_tolerance_is_made_exact():
    R = np.eye(3)
    R[0, 1] = 1e-9
    result = _minimal()
    result["T_cam_base"]["R"] = R.tolist()
    checked = np.array(validate_result(result, SOURCE)["T_cam_base"]["R"])
    assert np.max(np.abs(checked.T @ checked - np.eye(3))) < 1e-15
    result["T_cam_base"]["q_xyzw"] = [-x for x in result["T_cam_base"]["q_xyzw"]]  # the same rotation
    validate_result(result, SOURCE)


def test_messages_quote_little_user_data():
    shared: Any = ["x" * 10_000]
    for _ in range(40):  # a YAML alias bomb: 10 references per level, 40 levels
        shared = [shared] * 10
    for garbage in ("y" * 100_000, shared, {"k" * 5000: shared}, 10**5000, -(10**400)):
        result = _minimal()
        result["mirrors"] = [{"mirror": 1, "config": 0, "v": garbage}]
        with pytest.raises(DatasetError) as exc:
            validate_result(result, SOURCE)
        _assert_one_line(exc.value, SOURCE, "mirrors[0].v")
        result["points"] = {"k" * 5000: {"xyz": [1, 2, 3]}, "P": {"xyz": garbage}}
        del result["mirrors"]
        with pytest.raises(DatasetError) as exc:
            validate_result(result, SOURCE)
        _assert_one_line(exc.value, SOURCE, "points.P.xyz")


# --------------------------------------------------------------------------------------------------
# Readers take only validated results; a dataset that is not the result's names both files


def test_readers_refuse_corrupt_result_before_any_work(calibrated, tmp_path):
    ds, good = calibrated
    result = copy.deepcopy(good)
    result["mirrors"][3]["v"] = "abc"
    for call in (
        lambda: write_report(result, ds, tmp_path / "report", progress=False, source=SOURCE),
        lambda: compute_residuals(result, ds, source=SOURCE),
        lambda: write_ros_outputs(result, tmp_path / SOURCE),
    ):
        with pytest.raises(DatasetError) as exc:
            call()
        _assert_one_line(exc.value, SOURCE, "mirrors[3].v", "'abc'")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda r: r["mirrors"].pop(), ["mirror 2 configuration"]),
        (lambda r: r["points"].pop("P1"), ["'P1'"]),
        (lambda r: r["mirrors"].append({"mirror": 3, "config": 0, "v": [0, 0, 1]}), ["3 mirror(s)", "dataset 2"]),
        (lambda r: r.update(mirrors=None), ["mirror 1 configuration"]),
    ],
)
def test_foreign_dataset_names_both_files(calibrated, tmp_path, edit, words):
    ds, good = calibrated
    result = copy.deepcopy(good)
    edit(result)
    validate_result(result, SOURCE)  # a valid result, of another dataset
    with pytest.raises(DatasetError) as exc:
        write_report(result, ds, tmp_path / "report", progress=False, source=SOURCE)
    _assert_one_line(exc.value, SOURCE, str(ds.source), *words)
    assert not (tmp_path / "report").exists()


def test_full_report_of_a_result_with_every_optional_key_null(calibrated, tmp_path):
    """What the fuzz accepts, rendered: null optional keys, NaN statistics, extras of any type."""
    ds, good = calibrated
    result = copy.deepcopy(good)
    for key in ("T_base_cam", "covariance_cam_base", "sigma3_cam_base", "covariance_base_cam", "sigma3_base_cam",
                "covariance_base_cam_ros", "analytic"):
        result[key] = None
    result["T_cam_base"]["q_xyzw"] = None
    for entry in [*result["mirrors"], *result["points"].values()]:
        entry["sigma3_mm"] = None
    result["mirrors"][0]["sigma3_mm"] = [math.nan] * 3
    result["optimizer"] = {"iterations": None, "initial_error": math.nan, "converged": None,
                           "expected_final_error": math.nan}  # read by the summary now: a statistic, NaN allowed
    result["residuals"] = {"rms_px": math.nan, "max_px": None, "units": "abc", "outliers": None, "mean_px": None}
    paths = write_report(result, ds, tmp_path / "with", progress=False, source=SOURCE)
    assert paths["pdf"].read_bytes().startswith(b"%PDF")
    minimal = {"format": good["format"], "T_cam_base": good["T_cam_base"], "extra": [[{}]]}
    paths = write_report(minimal, None, tmp_path / "without", progress=False, source=SOURCE)
    assert "No dataset given" in paths["html"].read_text(encoding="utf-8")
    write_ros_outputs(minimal, tmp_path / SOURCE)


# --------------------------------------------------------------------------------------------------
# The command line: exit 2 and one line naming the file and the key


def _write(path: Path, text: str) -> str:
    path.write_text(text, encoding="utf-8")
    return str(path)


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda r: r["mirrors"][3].update(v="abc"), "mirrors[3].v"),
        (lambda r: r.update(analytic={"T_cam_base": [1, 2, 3]}), "analytic.T_cam_base"),
        (lambda r: r["points"]["P0"].update(xyz=["1", "2", "3"]), "points.P0.xyz[0]"),
        (lambda r: r.update(covariance_cam_base=[[0.0] * 6] * 5), "covariance_cam_base"),
        (lambda r: r["residuals"].update(rms_px={"a": 1}), "residuals.rms_px"),
        (lambda r: r["residuals"].update(outliers=[7]), "residuals.outliers[0]"),
        (lambda r: r["optimizer"].update(iterations=10**400), "optimizer.iterations"),
        (lambda r: r["T_base_cam"]["t"].__setitem__(1, math.nan), "T_base_cam.t[1]"),
        (lambda r: r["sigma3_cam_base"].update(position_mm="big"), "sigma3_cam_base.position_mm"),
    ],
)
def test_cli_report_on_corrupt_result_exits_2_naming_file_and_key(calibrated, tmp_path, capsys, edit, key):
    _, good = calibrated
    result = copy.deepcopy(good)
    edit(result)
    path = _write(tmp_path / SOURCE, json.dumps(result))
    assert main(["report", path, "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and len(err) < MAX_MESSAGE + 40 and "internal error" not in err, err
    assert key in err and SOURCE in err, err
    assert not (tmp_path / "out").exists()


def test_cli_report_with_a_foreign_dataset_exits_2_naming_both_files(calibrated, tmp_path, capsys):
    ds, good = calibrated
    other, _ = simulate_base_case(num_images=30, num_points=3, seed=2)
    dataset = _write(tmp_path / "dataset_b.json", json.dumps(dataset_to_dict(other)))
    result = _write(tmp_path / SOURCE, json.dumps(good))
    assert main(["report", result, dataset, "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "internal error" not in err, err
    assert SOURCE in err and "dataset_b.json" in err, err
