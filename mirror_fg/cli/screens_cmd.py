"""``mirror-fg calibrate CAPTURE`` where the capture gives several ``screens`` (:mod:`mirror_fg.io.screens_capture`,
:mod:`mirror_fg.solver.batch.screens`): detect each screen's images, calibrate each alone, then all in one graph;
write result@1 with every screen and their relative poses. Runner and printing only."""
from __future__ import annotations

import os
import time

from mirror_fg.cli.printing import EXIT_OK, _Printer

__all__ = ["calibrate_screens_input"]


def calibrate_screens_input(args, out: _Printer) -> int | None:
    """Calibrate ``args.input`` if it is a capture file with ``screens`` (a regular file: read here), else None
    (the ordinary ``calibrate`` goes on)."""
    source = os.fspath(args.input)
    if source == "-" or not os.path.isfile(source) or os.path.abspath(source).startswith(("/dev/", "/proc/")):
        return None
    from mirror_fg.io.fileio import NotTextError, load_structured
    from mirror_fg.io.screens_capture import is_screens_capture

    try:
        data = load_structured(source)
    except NotTextError:  # a photograph or a video given as the input: the ordinary path says what to give
        return None
    if not is_screens_capture(data):
        return None
    return _calibrate(args, out, data, source)


def _calibrate(args, out: _Printer, data: dict, source: str) -> int:
    from mirror_fg.cli.loading import detection_exclusions, print_detection_report
    from mirror_fg.core.errors import DatasetError
    from mirror_fg.core.gaze_error import gaze_summary_lines
    from mirror_fg.io.capture import capture_from_file_data
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.io.result import result_text
    from mirror_fg.io.screens_capture import screens_result, split_screens_capture
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.result.calibration import require_converged
    from mirror_fg.solver.batch.screens import calibrate_screens
    from mirror_fg.vision.detect import detect_capture

    if args.incremental:
        raise DatasetError(f"{source}: screens: several screens are calibrated in one batch; drop --incremental")
    start = time.perf_counter()
    plan = OutputPlan(inputs=[source])
    target_path = plan.add(args.output, "result")
    targets, captures = split_screens_capture(data, source)
    datasets, alone, excluded = {}, {}, []
    for name, capture_data in captures.items():
        capture = capture_from_file_data(capture_data, source)
        plan.add_inputs(capture.input_files())
        out.info(f"screen {name}:")
        dataset, reports = detect_capture(capture, progress=out.progress)
        print_detection_report(out, reports)
        datasets[name] = dataset
        alone[name] = require_converged(calibrate(dataset, robust=args.robust), f"{source} (screen {name})",
                                        accept_poor_fit=args.accept_poor_fit)
        left_out = _as_dicts(detection_exclusions(reports)) + _as_dicts(alone[name].excluded)
        excluded += [{**e, "image": f"{name}/{e['image']}"} for e in left_out]  # images are named screen/image
    calibration = calibrate_screens(datasets, alone)
    result = screens_result(calibration, targets, args.viewing_distance)
    result["excluded"] = excluded
    written = plan.commit({target_path: result_text(result, target_path)})
    _print_screens(out, result, args.viewing_distance, gaze_summary_lines)
    out.info(f"time {time.perf_counter() - start:.2f} s")
    out.info("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def _as_dicts(exclusions: list) -> list[dict]:
    """result@1 ``excluded`` entries of :class:`~mirror_fg.solver.result.calibration.Exclusion` values."""
    return [{"image": e.image, "point": e.point, "reason": e.reason, "sigmas": e.sigmas} for e in exclusions]


def _print_screens(out: _Printer, result: dict, viewing_distance: float, gaze_summary_lines) -> None:  # noqa: ANN001
    for name, block in result["screens"].items():
        t, s = block["T_cam_screen"]["t"], block["sigma3"]
        out.info(f"screen {name}: T_cam_screen t [{t[0]:.5f}, {t[1]:.5f}, {t[2]:.5f}] m (its top-left corner, camera "
                 f"frame); 3-sigma rotation ±{_triple(s['rotation_deg'], 3)} deg, position ±{_triple(s['position_mm'], 2)} mm")
        for line in gaze_summary_lines(block):
            out.info("  " + line)
    for pair in result["screen_pairs"]:
        t, s = pair["T"]["t"], pair["sigma3"]
        out.info(f"screen {pair['from']} in screen {pair['to']}'s frame: t [{t[0]:.5f}, {t[1]:.5f}, {t[2]:.5f}] m; 3-sigma "
                 f"rotation ±{_triple(s['rotation_deg'], 3)} deg, position ±{_triple(s['position_mm'], 2)} mm")
    residuals = result.get("residuals") or {}
    if "rms_px" in residuals:
        out.info(f"residuals (every screen): RMS {residuals['rms_px']:.3f} px, largest {residuals['max_px']:.3f} px")


def _triple(values: list[float], digits: int) -> str:
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"
