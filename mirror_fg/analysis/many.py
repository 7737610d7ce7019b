"""Calibrating many captures or datasets (a fleet of robots) on the Dask engine of ``analysis/montecarlo.py``.

Each input goes through the same path as ``mirror-fg calibrate``: read once (a capture@1 is detected
first, :func:`mirror_fg.vision.detect.load_input`), ``calibrate``, a converged result written all-or-nothing by
``io.output.OutputPlan`` as ``OUT_DIR/<input stem>.result.json`` with its ROS files beside it. One
failure never stops the rest: it becomes a row with its reason, also an input whose worker keeps dying (out of
memory?).

A small job runs in this process: a local Dask cluster costs more to start than it saves
(:func:`runs_in_process`, the rule and its measurement). The rows, files and exit codes are the same either way;
only an input that kills its process (not an exception: those are rows) stops an in-process run.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.analysis.montecarlo import (
    CONNECT_TIMEOUT_S,
    lost_reason,
    run_trials,
    scheduler_address,
)

__all__ = ["calibrate_many", "calibrate_one", "result_path_for", "runs_in_process"]

#: Below this estimated work (seconds of calibration in one process) a job runs in this process. A local cluster
#: of 2 workers cost about 1.5 s on a quiet 2-core machine (start, each worker importing GTSAM, close: three
#: 200-image datasets took 2.7 s through it against 1.3 s in one process, both as commands) and saves at most half
#: the work: it pays from about 2 x 1.5 s of work. Under a load of 8 the start-up grows (the same three: 9.5 s
#: through it, 2.8 s in one process, 2.5 s for one alone).
IN_PROCESS_BELOW_S = 3.0
#: Estimated calibration seconds per input and per byte of its data (a dataset@1 file, or the photographs and
#: videos a capture@1 names), measured in one process on a quiet machine: simulated datasets of 200, 1,000 and
#: 3,000 images (53 kB, 265 kB, 798 kB) took 0.17, 0.28 and 0.74 s.
_SECONDS_PER_INPUT = 0.1
_SECONDS_PER_BYTE = 0.8e-6


def _estimated_seconds(path: str | os.PathLike[str]) -> float:
    """Calibration time of one input, from the size of its data (unreadable: nothing; its row will say why)."""
    try:
        size = os.path.getsize(path)
        if Path(path).suffix.lower() in (".yaml", ".yml"):  # a capture: detection reads what it names
            from mirror_fg.io.capture import load_capture

            size = sum(os.path.getsize(name) for name in load_capture(path).input_files())
    except Exception:  # an estimate only; calibrate_one reports the input's problem
        return _SECONDS_PER_INPUT
    return _SECONDS_PER_INPUT + _SECONDS_PER_BYTE * size


def runs_in_process(inputs: list[str | os.PathLike[str]], workers: int) -> bool:
    """Whether calibrating ``inputs`` in this process is faster than starting a local cluster of ``workers``:
    one worker, or an estimated total below ``IN_PROCESS_BELOW_S`` seconds."""
    return workers <= 1 or sum(_estimated_seconds(path) for path in inputs) < IN_PROCESS_BELOW_S


def result_path_for(path: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> Path:
    """``OUT_DIR/<input file name without its extension>.result.json``."""
    return Path(out_dir) / (Path(path).stem + ".result.json")


def calibrate_one(path: str, out_dir: str, ros: bool = True, registry: str | None = None,
                  robot: str | None = None) -> dict:
    """Calibrate one input and write its result: a row ``{input, status, reason, result, ...}``, never
    an exception (a failure is ``status: "failed"`` with the reason). ``registry``: also record it there for
    ``robot`` (None: the input's stem), from this worker, after the file is written; a record not stored is
    the row's ``registry_error`` (the result stays ``ok``)."""
    from mirror_fg.core.errors import MirrorFgError, SolveError
    from mirror_fg.io.calibration_files import plan_calibration_outputs
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.result.calibration import require_converged
    from mirror_fg.report.verdict import with_verdict
    from mirror_fg.vision.detect import load_input

    row: dict[str, Any] = {"input": os.fspath(path), "status": "failed", "reason": "", "result": None}
    try:
        target = result_path_for(path, out_dir)
        outputs = plan_calibration_outputs([path], target, ros=ros)
        dataset, _ = load_input(path, outputs.plan, on_capture=outputs.use_capture)
        if dataset.camera is not None and dataset.camera.estimate:
            outputs.expect_camera()
        if dataset.cameras is not None:
            outputs.expect_cameras()
        calibration = require_converged(calibrate(dataset), dataset.source)
        result = with_verdict(calibration.to_dict(), dataset)  # the one verdict, as calibrate stores it
        outputs.write(result)
        sigma3, sigma3_base = result["sigma3_cam_base"], result["sigma3_base_cam"]
        if sigma3 is None or sigma3_base is None:  # calibrate() computes the covariance
            raise SolveError(f"{dataset.source}: no covariance in the calibration")
        row.update(status="ok", result=os.fspath(target), images=len(dataset.images),
                   base_is_camera=not dataset.fiducials,  # no known target: T_cam_base is the identity, not estimated
                   t_cam_base=[float(x) for x in calibration.t_cam_base],
                   t_base_cam=result["T_base_cam"]["t"],
                   sigma3_position_mm=sigma3["position_mm"],  # T_cam_base, camera axes
                   sigma3_rotation_deg=sigma3["rotation_deg"],
                   sigma3_base_cam=sigma3_base,  # the camera's pose on the robot, base axes
                   rms=result["residuals"]["rms_px"], iterations=calibration.iterations)
        from mirror_fg.registry.cli import record_row

        row["registry_error"] = record_row(registry, robot, result, path, os.fspath(target))
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
    connect_timeout: float = CONNECT_TIMEOUT_S,
    in_process: bool | None = None,
    registry: Any = None,
) -> list[dict]:
    """Calibrate every input (dataset@1 or capture@1 files) into ``out_dir``, on a local Dask cluster of
    ``workers`` processes or the scheduler at ``scheduler`` (a DatasetError naming it if none answers within
    ``connect_timeout`` seconds); rows in the order of ``inputs`` (:func:`calibrate_one`: ``input``, ``status``
    ok/failed, ``reason``, ``result`` path, key figures). in_process: run here instead of on a local cluster
    (None: when :func:`runs_in_process` says it is faster; ignored with a ``scheduler``). registry: a
    ``registry.cli.RegistryTarget`` each worker records its run in (the row's ``registry_error`` if not stored)."""
    targets: dict[Path, str] = {}
    for path in inputs:  # two inputs must not write one result
        target = result_path_for(path, out_dir)
        if target in targets:
            raise DatasetError(f"{os.fspath(path)} and {targets[target]} would both write {target}: rename one")
        targets[target] = os.fspath(path)
    if scheduler is not None:
        scheduler_address(scheduler)  # a malformed address before anything is made
    created = not os.path.isdir(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    todo = [{"path": os.fspath(p), "out_dir": os.fspath(out_dir)} for p in inputs]
    if registry is not None:
        todo = [dict(item, registry=registry.url, robot=registry.robot) for item in todo]
    if in_process is None:
        in_process = runs_in_process(inputs, workers)
    jobs = 1 if in_process else workers
    try:
        rows = run_trials(calibrate_one, todo, [], total=len(todo), desc="calibrations", progress=progress,
                          jobs=jobs, scheduler=scheduler, connect_timeout=connect_timeout, on_lost=_lost_row)
    except BaseException:
        if created and not os.listdir(out_dir):  # no scheduler, say: leave no empty directory behind
            os.rmdir(out_dir)
        raise
    order = {item["path"]: n for n, item in enumerate(todo)}
    return sorted(rows, key=lambda row: order[row["input"]])


def _lost_row(kwargs: dict, error: BaseException) -> dict:
    """The failed row of an input whose worker died (``KilledWorker``), as :func:`calibrate_one` would give."""
    return {"input": kwargs["path"], "status": "failed", "reason": lost_reason(error), "result": None}
