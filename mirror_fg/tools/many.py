"""Calibrating many captures or datasets (a fleet of robots) on the Dask engine of ``tools/montecarlo.py``.

Each input goes through the same path as ``mirror-fg calibrate``: read once (a capture@1 is detected
first, :func:`mirror_fg.vision.detect.load_input`), ``calibrate``, a converged result written all-or-nothing by
``io.output.OutputPlan`` as ``OUT_DIR/<input stem>.result.json`` with its ROS files beside it. One
failure never stops the rest: it becomes a row with its reason.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.tools.montecarlo import run_trials

__all__ = ["calibrate_one", "calibrate_many", "result_path_for"]


def result_path_for(path: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> Path:
    """``OUT_DIR/<input file name without its extension>.result.json``."""
    return Path(out_dir) / (Path(path).stem + ".result.json")


def calibrate_one(path: str, out_dir: str, ros: bool = True) -> dict:
    """Calibrate one input and write its result: a row ``{input, status, reason, result, ...}``, never
    an exception (a failure is ``status: "failed"`` with the reason)."""
    from mirror_fg.core.errors import MirrorFgError, SolveError
    from mirror_fg.io.calibration_files import plan_calibration_outputs
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.calibration import require_converged
    from mirror_fg.vision.detect import load_input

    row: dict[str, Any] = {"input": os.fspath(path), "status": "failed", "reason": "", "result": None}
    try:
        target = result_path_for(path, out_dir)
        outputs = plan_calibration_outputs([path], target, ros=ros)
        dataset, _ = load_input(path, outputs.plan, on_capture=outputs.use_capture)
        if dataset.camera is not None and dataset.camera.estimate:
            outputs.expect_camera()
        calibration = require_converged(calibrate(dataset), dataset.source)
        result = calibration.to_dict()
        outputs.write(result)
        sigma3, sigma3_base = result["sigma3_cam_base"], result["sigma3_base_cam"]
        if sigma3 is None or sigma3_base is None:  # calibrate() computes the covariance
            raise SolveError(f"{dataset.source}: no covariance in the calibration")
        row.update(status="ok", result=os.fspath(target), images=len(dataset.images),
                   t_cam_base=[float(x) for x in calibration.t_cam_base],
                   t_base_cam=result["T_base_cam"]["t"],
                   sigma3_position_mm=sigma3["position_mm"],  # T_cam_base, camera axes
                   sigma3_rotation_deg=sigma3["rotation_deg"],
                   sigma3_base_cam=sigma3_base,  # the camera's pose on the robot, base axes
                   rms=result["residuals"]["rms_px"], iterations=calibration.iterations)
    except MirrorFgError as error:
        row["reason"] = str(error)
    except Exception as error:  # one bad input must not stop the others: report it, go on
        row["reason"] = f"{type(error).__name__}: {error}"
    return row


def calibrate_many(
    inputs: list[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool = True,
) -> list[dict]:
    """Calibrate every input (dataset@1 or capture@1 files) into ``out_dir``, on a local Dask cluster of
    ``workers`` processes or the scheduler at ``scheduler``; rows in the order of ``inputs``
    (:func:`calibrate_one`: ``input``, ``status`` ok/failed, ``reason``, ``result`` path, key figures)."""
    targets: dict[Path, str] = {}
    for path in inputs:  # two inputs must not write one result
        target = result_path_for(path, out_dir)
        if target in targets:
            raise DatasetError(f"{os.fspath(path)} and {targets[target]} would both write {target}: rename one")
        targets[target] = os.fspath(path)
    os.makedirs(out_dir, exist_ok=True)
    todo = [{"path": os.fspath(p), "out_dir": os.fspath(out_dir)} for p in inputs]
    rows = run_trials(calibrate_one, todo, [], total=len(todo), desc="calibrations", progress=progress,
                      jobs=workers, scheduler=scheduler)
    order = {item["path"]: n for n, item in enumerate(todo)}
    return sorted(rows, key=lambda row: order[row["input"]])
