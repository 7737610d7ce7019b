"""Hostile input and faults at the command line: one test (or parametrised family) per class.

Data loss, hangs and runaway memory, silent wrong answers, internal errors that must be exit 2 with
one line. Each test fails on the code before the fix (noted per test).
"""
import copy
import dataclasses
import json
import os
import resource
import stat
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import mirror_fg
from mirror_fg.cli import main
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.simulate.tree import simulate_base_case

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args: str, stdin=None, stdout=subprocess.PIPE, timeout: float = 120, memory_gb: float = 3.0,
            cwd=None) -> subprocess.CompletedProcess:
    """``python -m mirror_fg.cli ARGS`` in a child with its address space capped (a bomb is killed, not us)."""
    limit = int(memory_gb * 2**30)

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run([sys.executable, "-m", "mirror_fg.cli", *args], stdin=stdin, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=timeout, preexec_fn=cap, cwd=cwd)


def one_error_line(proc: subprocess.CompletedProcess, code: int, *words: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for word in words:
        assert word.lower() in lines[0].lower(), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def dataset_dict() -> dict:
    dataset, _ = simulate_base_case(num_images=45, num_points=2, pixel_sigma=0.5, seed=5)
    return dataset_to_dict(dataset)


@pytest.fixture
def data(tmp_path, dataset_dict) -> Path:
    path = tmp_path / "d.json"
    path.write_text(json.dumps(dataset_dict))
    return path


# --- data loss ------------------------------------------------------------------------------------


def test_output_that_is_the_input_is_refused_before_any_work(data, tmp_path, capsys):
    """Before: `calibrate d.json -o d.json` replaced the dataset with the result."""
    before = data.read_bytes()
    link = tmp_path / "link.json"
    link.symlink_to(data)
    for output in (data, link, tmp_path / "." / "d.json"):
        assert main(["calibrate", str(data), "-o", str(output)]) == 2
        err = capsys.readouterr().err
        assert "input" in err and err.count("\n") == 1, err
    assert data.read_bytes() == before
    assert not (tmp_path / "d.ros.yaml").exists()


def test_side_file_that_is_an_input_or_a_strangers_file_is_never_replaced(data, tmp_path, capsys):
    """Before: `<stem>.ros.yaml` / `<stem>.urdf.xml` replaced whatever had that name."""
    robot_urdf = tmp_path / "r.urdf.xml"
    robot_urdf.write_text("<robot name='mine'/>\n")
    assert main(["calibrate", str(data), "-o", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "r.urdf.xml" in err and "not written by mirror-fg" in err
    assert robot_urdf.read_text() == "<robot name='mine'/>\n"
    assert not (tmp_path / "r.json").exists()
    # The input itself named like a side file.
    side_input = tmp_path / "q.ros.yaml"
    side_input.write_text(data.read_text())
    before = side_input.read_bytes()
    assert main(["calibrate", str(side_input), "-o", str(tmp_path / "q.json")]) == 2
    assert "input" in capsys.readouterr().err
    assert side_input.read_bytes() == before
    # Our own side files from an earlier run are replaced as usual.
    assert main(["calibrate", str(data), "-o", str(tmp_path / "ok.json")]) == 0
    assert main(["calibrate", str(data), "-o", str(tmp_path / "ok.json")]) == 0


def test_result_and_side_files_are_all_or_nothing(data, tmp_path, capsys, monkeypatch):
    """Before: with a directory where r.ros.yaml goes, r.json was replaced and the run exited 1."""
    result = tmp_path / "r.json"
    result.write_text("old result\n")
    (tmp_path / "r.ros.yaml").mkdir()
    assert main(["calibrate", str(data), "-o", str(result)]) == 2
    assert "r.ros.yaml" in capsys.readouterr().err
    assert result.read_text() == "old result\n"
    # A failure while the files are written: none is replaced, no temporary file is left.
    os.rmdir(tmp_path / "r.ros.yaml")
    real_fsync, calls = os.fsync, []

    def failing_fsync(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 3:  # the third file (the URDF)
            raise OSError(28, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", failing_fsync)
    assert main(["calibrate", str(data), "-o", str(result)]) == 2
    assert "No space left" in capsys.readouterr().err
    assert result.read_text() == "old result\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.json", "r.json"]


def test_a_device_is_written_into_never_replaced_and_a_fifo_is_refused(data, tmp_path, capsys):
    """Before: as root, `-o /dev/null` replaced the device with a regular file."""
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    assert main(["calibrate", str(data), "-o", str(fifo)]) == 2
    assert "named pipe" in capsys.readouterr().err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    device = tmp_path / "null"
    try:
        os.mknod(device, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a /dev/null of our own
    except (PermissionError, OSError):
        device = Path(os.devnull)
    assert main(["calibrate", str(data), "-o", str(device)]) == 0
    assert stat.S_ISCHR(os.stat(device).st_mode)
    assert not list(device.parent.glob("null.ros.yaml"))


@pytest.mark.parametrize("how", ["dev_full", "closed_pipe"])
def test_a_broken_stdout_neither_changes_the_exit_status_nor_the_files(data, tmp_path, how):
    """Before: a broken stdout after the result was replaced turned success into exit 1."""
    out = tmp_path / "r.json"
    if how == "dev_full":
        with open("/dev/full", "w") as full:
            proc = run_cli("calibrate", str(data), "-o", str(out), stdout=full)
        stderr, code = proc.stderr, proc.returncode
    else:
        child = subprocess.Popen([sys.executable, "-m", "mirror_fg.cli", "calibrate", str(data), "-o", str(out)],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        child.stdout.close()  # nobody reads: every write to stdout fails with EPIPE
        stderr = child.stderr.read()
        code = child.wait(timeout=120)
    assert code == 0, stderr
    assert "standard output failed" in stderr and "Traceback" not in stderr and "Exception ignored" not in stderr
    assert json.loads(out.read_text())["format"] == "mirror-fg/result@1"
    assert (tmp_path / "r.ros.yaml").exists()


# --- hangs and runaway memory --------------------------------------------------------------------

BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(9)
)


def test_yaml_alias_bombs_are_refused_quickly(tmp_path):
    """Before: memory grew ~1 GB every few seconds (the message helper expanded the aliased value)."""
    capture = tmp_path / "bomb.yaml"
    capture.write_text("format: mirror-fg/capture@1\nnum_mirrors: 1\n" + BOMB)
    one_error_line(run_cli("calibrate", str(capture), "-o", str(tmp_path / "r.json"), timeout=60), 2,
                   "bomb.yaml", "aliases")
    result = tmp_path / "bomb_result.yaml"
    result.write_text("format: mirror-fg/result@1\n" + BOMB)
    one_error_line(run_cli("report", str(result), "-o", str(tmp_path / "rep"), timeout=60), 2, "aliases")
    layout = tmp_path / "bomb_fiducials.yaml"
    layout.write_text(BOMB)
    one_error_line(run_cli("plan", "--fiducials-file", str(layout), timeout=60), 2, "aliases")


def test_endless_and_streamed_inputs_are_read_once_and_bounded(data, tmp_path):
    """Before: the input was read twice (to sniff a capture): stdin refused wrongly, a FIFO hung."""
    one_error_line(run_cli("calibrate", "/dev/zero", "-o", str(tmp_path / "z.json"), timeout=60), 2,
                   "/dev/zero", "larger than")
    with open(data) as handle:
        proc = run_cli("calibrate", "/dev/stdin", "-o", str(tmp_path / "s.json"), stdin=handle)
    assert proc.returncode == 0, proc.stderr
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_bytes(data.read_bytes()))
    writer.start()
    proc = run_cli("calibrate", str(fifo), "-o", str(tmp_path / "f.json"), timeout=120)
    writer.join(timeout=10)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("name, text, words", [
    ("deep.json", "[" * 100_000 + "]" * 100_000, ["nested"]),
    ("deep.yaml", "a: " + "[" * 20_000 + "]" * 20_000, ["nested"]),
    ("big.json", None, ["num_mirrors"]),
    ("big.yaml", "format: mirror-fg/capture@1\nnum_mirrors: " + "9" * 400 + "\n", ["num_mirrors"]),
])
def test_deep_nesting_and_huge_integers_are_bad_input(tmp_path, dataset_dict, name, text, words):
    """Before: RecursionError / OverflowError (exit 1, internal error)."""
    if text is None:
        text = json.dumps(dataset_dict).replace('"num_mirrors": 2', '"num_mirrors": ' + "9" * 400)
    path = tmp_path / name
    path.write_text(text)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 2


def test_huge_integers_in_a_dataset_are_named(tmp_path, dataset_dict, capsys):
    d = copy.deepcopy(dataset_dict)
    text = json.dumps(d).replace('"width": 1024', '"width": ' + "1" * 30)
    path = tmp_path / "w.json"
    path.write_text(text)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 2
    assert "width" in capsys.readouterr().err


# --- silent wrong answers ------------------------------------------------------------------------


def test_the_answer_does_not_depend_on_a_uniform_pixel_sigma(dataset_dict):
    """Before: pixel_sigma 1e6 stopped LM 20 mm away, 1e12 after one iteration 60 mm away, exit 0.
    (A file now refuses a sigma beyond the image diagonal; the solver itself stays scale-free.)"""
    answers = []
    dataset = dataset_from_dict(copy.deepcopy(dataset_dict))
    for sigma in (0.5, 1e6, 1e12, 1e-6):
        cal = mirror_fg.calibrate(dataclasses.replace(dataset, pixel_sigma=sigma))
        assert cal.converged
        answers.append((cal.t_cam_base, cal.R_cam_base, cal.sigma3_position_mm / sigma))
    for t, R, s3 in answers[1:]:
        np.testing.assert_allclose(t, answers[0][0], atol=1e-9)
        np.testing.assert_allclose(R, answers[0][1], atol=1e-9)
        np.testing.assert_allclose(s3, answers[0][2], rtol=1e-6)


@pytest.mark.parametrize("where, bad, meant", [
    ("camera", "distortion", "dist"),
    ("top", "pixel_sigm", "pixel_sigma"),
    ("image", "observation", "observations"),
    ("camera", "fxx", "fx"),
])
def test_a_misspelt_key_is_refused_with_a_did_you_mean(tmp_path, dataset_dict, capsys, where, bad, meant):
    """Before: `"distortion"` instead of `"dist"` was dropped: exit 0 and a pose 20 mm off."""
    d = copy.deepcopy(dataset_dict)
    target = {"camera": d["camera"], "top": d, "image": d["images"][3]}[where]
    target[bad] = [0.1, 0.0, 0.0, 0.0, 0.0] if where == "camera" else target.get(meant, 1.0)
    path = tmp_path / "typo.json"
    path.write_text(json.dumps(d))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert f"unknown key '{bad}'" in err and f"did you mean '{meant}'" in err, err


def test_pixels_outside_the_image_are_refused_by_batch_and_incremental_alike(tmp_path, dataset_dict, capsys):
    """Before: batch exit 3, --incremental wrote converged: false with RMS 564 px and exit 0."""
    d = copy.deepcopy(dataset_dict)
    d["images"][7]["observations"]["F1"] = [5000.0, -300.0]
    path = tmp_path / "far.json"
    path.write_text(json.dumps(d))
    messages = []
    for extra in ([], ["--incremental"]):
        assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), *extra]) == 2
        messages.append(capsys.readouterr().err)
    assert messages[0] == messages[1]
    assert "outside the 1024x768 image" in messages[0] and "F1" in messages[0]
    assert not (tmp_path / "r.json").exists()
    inc = mirror_fg.IncrementalCalibrator(dataset_from_dict(dataset_dict))
    with pytest.raises(DatasetError, match="outside"):
        inc.add_image({"id": "far", "mirror_configs": [0, 0], "observations": {"F0": [1e9, -1e9]}})


def test_incremental_refuses_a_result_that_did_not_converge_like_the_batch(data, tmp_path, capsys, monkeypatch):
    from mirror_fg.solver.incremental import calibrator as incremental

    real = incremental.IncrementalCalibrator.calibration

    def unconverged(self, full=False):
        cal = real(self, full)
        if full:
            cal.converged = False
        return cal

    monkeypatch.setattr(incremental.IncrementalCalibrator, "calibration", unconverged)
    assert main(["calibrate", str(data), "-o", str(tmp_path / "r.json"), "--incremental"]) == 3
    assert "did not converge" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


# --- internal errors that must be exit 2 with one line -------------------------------------------


@pytest.mark.parametrize("args", [
    ["simulate", "--images", "0"], ["simulate", "--sigma", "-1"], ["simulate", "--mirrors", "0"],
    ["simulate", "--points", "-1"], ["simulate", "--sigma", "inf"], ["simulate", "--sigma", "nan"],
    ["plan", "--images", "0"], ["plan", "--sigma", "inf"], ["plan", "--mirrors", "0"], ["plan", "--tilt", "-5"],
    ["plan", "--draws", "0"], ["plan", "--placements", "2"],
])
def test_out_of_range_arguments_are_one_line(tmp_path, args):
    """Before: exit 1 internal errors (e.g. --images 0)."""
    if args[0] == "simulate":
        args = [*args, "-o", str(tmp_path / "s.json")]
    line = one_error_line(run_cli(*args, timeout=60), 2, args[1])
    assert len(line) < 200


def test_output_paths_that_cannot_be_written_are_refused_before_the_work(data, tmp_path, capsys):
    """Before: `-o` under a regular file or an existing directory, `report -o` a file: exit 1 after the work."""
    for output, words in ((data / "r.json", "is a file"), (tmp_path, "is a directory")):
        assert main(["calibrate", str(data), "-o", str(output)]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert main(["calibrate", str(data), "-o", str(tmp_path / "r.json")]) == 0
    capsys.readouterr()
    report_file = tmp_path / "report_here"
    report_file.write_text("keep me")
    assert main(["report", str(tmp_path / "r.json"), "-o", str(report_file)]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert report_file.read_text() == "keep me"
    assert main(["simulate", "-o", str(data / "s.json")]) == 2


def test_the_api_takes_a_dataset_dict_and_refuses_anything_else(dataset_dict):
    """Before: `mirror_fg.calibrate(a_dict)` raised AttributeError."""
    from_dict = mirror_fg.calibrate(dataset_dict)
    from_dataset = mirror_fg.calibrate(dataset_from_dict(dataset_dict))
    np.testing.assert_array_equal(from_dict.t_cam_base, from_dataset.t_cam_base)
    with pytest.raises(DatasetError, match="expected a mirror_fg.Dataset"):
        mirror_fg.calibrate("d.json")


def test_error_lines_quote_little_user_data(tmp_path, capsys):
    directory = tmp_path / ("x" * 200) / ("z" * 200)
    directory.mkdir(parents=True)
    path = directory / ("y" * 200 + ".json")
    path.write_text('{"format": "' + "y" * 5000 + '"}')
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and len(line) < 300, line


def test_detect_reads_its_capture_once(tmp_path):
    """A capture given on standard input (read once) is detected; a dataset is refused as not a capture."""
    capture = REPO / "tests" / "data" / "capture" / "rendered" / "capture.yaml"
    with open(capture) as handle:  # through a pipe, relative image paths are taken from the working directory
        proc = run_cli("detect", "/dev/stdin", "-o", str(tmp_path / "d.json"), stdin=handle, cwd=capture.parent)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "d.json").read_text())["format"] == "mirror-fg/dataset@1"
    data = tmp_path / "data.json"
    data.write_text((tmp_path / "d.json").read_text())
    one_error_line(run_cli("detect", str(data), "-o", str(tmp_path / "e.json")), 2, "not a capture")


@pytest.mark.parametrize("key, value, message", [
    ("pixel_sigma", 1e300, "pixel_sigma must be between 1e-06 and"),
    ("pixel_sigma", 1e-300, "pixel_sigma must be between 1e-06 and"),
    ("pixel_sigma", 1e4, "px (the image diagonal), got 10000"),
    ("point_sigma", 1e300, "point_sigma: point 'F0': sigma must be between 1e-06 and"),
])
def test_a_sigma_no_measurement_can_have_is_refused_in_one_line(dataset_dict, tmp_path, capsys, key, value, message):
    """Before: pixel_sigma or point_sigma 1e300 printed numpy overflow warnings, then 'cannot solve' (exit 3)."""
    d = copy.deepcopy(dataset_dict)
    if key == "point_sigma":
        d["point_sigma"] = {"F0": value}
    else:
        d[key] = value
    path = tmp_path / "sigma.json"
    path.write_text(json.dumps(d))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "out.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "sigma.json" in err, err
    assert not (tmp_path / "out.json").exists()
