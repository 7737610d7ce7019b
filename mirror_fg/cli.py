"""Command line: ``mirror-fg simulate | calibrate | detect | plan | report``. Parsing and printing only.

Exit status: 0 success, 2 bad input, 3 could not solve (degenerate data, no convergence).
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_BAD_INPUT, EXIT_UNSOLVABLE, EXIT_INTERNAL = 0, 2, 3, 1

EPILOG = """exit status: 0 success, 2 bad input (the message names the file, image or point),
3 could not solve (degenerate data, no convergence), 1 internal error.
frames: T_cam_base maps base points into the camera (Cp = R Bp + t, OpenCV camera axes:
x right, y down, z forward); T_base_cam is its inverse, the camera's pose on the robot."""


class _Printer:
    def __init__(self, quiet: bool, verbose: bool):
        self.quiet, self.verbose = quiet, verbose

    def info(self, text: str = "") -> None:
        if not self.quiet:
            print(text)

    def detail(self, text: str) -> None:
        if self.verbose and not self.quiet:
            print(text)

    @property
    def progress(self) -> bool:
        return not self.quiet and sys.stderr.isatty()


def _add_common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    group.add_argument("-v", "--verbose", action="store_true", help="print more detail (and tracebacks of internal errors)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mirror-fg",
        description="Calibrate a camera to a robot base it sees only through planar mirrors "
        "(Hesch, Mourikis & Roumeliotis, ECCV 2010): analytical solution, GTSAM MLE, 3-sigma bounds.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sim = sub.add_parser("simulate", help="write a synthetic dataset and its ground truth",
                         description="Write a synthetic mirror-fg/dataset@1 (the paper's Sect. 7 base case by "
                         "default) and, beside it, <name>.truth.json with the true unknowns.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    sim.add_argument("-o", "--output", required=True, type=Path, help="dataset file to write (JSON)")
    sim.add_argument("--mirrors", type=int, default=2, help="number of mirrors Nv (default 2)")
    sim.add_argument("--images", type=int, default=200, help="number of images (base case; default 200)")
    sim.add_argument("--points", type=int, default=0, help="reconstruction points near the fiducials (default 0)")
    sim.add_argument("--sigma", type=float, default=1.0, help="pixel noise standard deviation, pixels (default 1.0)")
    sim.add_argument("--fiducials", type=int, default=3, choices=[3, 4], help="3 (paper) or 4 fiducials")
    sim.add_argument("--distance", type=float, default=0.5, help="camera-to-mirror distance, metres (default 0.5)")
    sim.add_argument("--placements", type=int, default=3, help="placements of mirror 1 (default 3)")
    sim.add_argument("--tree", action="store_true", help="minimal tree instead: 3 placements per node, 3^Nv images")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    _add_common(sim)

    cal = sub.add_parser("calibrate", help="analytical solution + MLE from a dataset or capture file",
                         description="Calibrate from a mirror-fg/dataset@1 (or a mirror-fg/capture@1, detected "
                         "first): analytical solution, Levenberg-Marquardt MLE, covariances. Writes a "
                         "mirror-fg/result@1 (JSON, or YAML when the name ends in .yaml) atomically, and beside "
                         "it <name>.ros.yaml and <name>.urdf.xml.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    cal.add_argument("input", type=Path, help="dataset@1 JSON or capture@1 YAML/JSON file")
    cal.add_argument("-o", "--output", required=True, type=Path, help="result file (.json or .yaml)")
    cal.add_argument("--robust", choices=["huber", "cauchy"], help="robust kernel on every measurement (threshold 1.345 sigma)")
    cal.add_argument("--incremental", action="store_true", help="iSAM2: stream the images in file order")
    cal.add_argument("--every", type=int, default=25, help="with --incremental: progress line every N images (default 25)")
    cal.add_argument("--base-frame", default="base_link", help="base frame name for the ROS outputs (default base_link)")
    cal.add_argument("--camera-frame", default="camera_optical_frame",
                     help="camera frame name for the ROS outputs (default camera_optical_frame)")
    cal.add_argument("--no-ros", action="store_true", help="do not write the ROS/URDF outputs beside the result")
    _add_common(cal)

    det = sub.add_parser("detect", help="detect fiducials in photographs or a video (capture@1 -> dataset@1)",
                         description="Detect the target in the images or video of a mirror-fg/capture@1 file and "
                         "write a mirror-fg/dataset@1 (pixels).", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    det.add_argument("capture", type=Path, help="capture@1 YAML or JSON file")
    det.add_argument("-o", "--output", required=True, type=Path, help="dataset file to write (JSON)")
    _add_common(det)

    pln = sub.add_parser("plan", help="Cramer-Rao 3-sigma bounds of a setup before any data is taken",
                         description="Predict the best achievable 3-sigma bounds on T_cam_base (Cramer-Rao, "
                         "inverse Fisher information at simulated truths) for a described setup, so you can choose "
                         "how many images and which mirror tilts to use before recording.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    pln.add_argument("--mirrors", type=int, default=2, help="number of mirrors Nv (default 2)")
    pln.add_argument("--placements", type=int, default=3,
                     help="placements of each mirror but the last per node (>= 3; default 3)")
    pln.add_argument("--images", type=int, default=200, help="number of images (default 200)")
    pln.add_argument("--fiducials", type=int, default=3, choices=[3, 4],
                     help="the paper's 20 cm right triangle (3) or with a point 15 cm off its plane (4)")
    pln.add_argument("--fiducials-file", type=Path,
                     help="JSON {name: [x, y, z]} base-frame fiducial layout, metres (overrides --fiducials)")
    pln.add_argument("--points", type=int, default=0, help="reconstruction points within 10 cm of the fiducials")
    pln.add_argument("--distance", type=float, default=0.5, help="camera-to-mirror distance, metres (default 0.5)")
    pln.add_argument("--tilt", type=float, default=30.0, help="largest mirror tilt, degrees (default 30)")
    pln.add_argument("--sigma", type=float, default=1.0, help="pixel noise standard deviation, pixels (default 1)")
    pln.add_argument("--focal", type=float, help="focal length, pixels (default: the simulator's 800)")
    pln.add_argument("--draws", type=int, default=5, help="random scenes averaged (default 5)")
    pln.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    pln.add_argument("--json", type=Path, help="also write the bounds to this JSON file")
    _add_common(pln)

    rep = sub.add_parser("report", help="HTML + PDF report of a result",
                         description="Write report.html (self-contained) and report.pdf: summary, residuals, "
                         "3D scene, correlations.", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    rep.add_argument("result", type=Path, help="result@1 file")
    rep.add_argument("dataset", type=Path, nargs="?", help="dataset@1 the result came from (enables residual plots)")
    rep.add_argument("-o", "--output", required=True, type=Path, help="output directory")
    rep.add_argument("--base-frame", default="base_link", help="base frame name in the ROS snippets (default base_link)")
    rep.add_argument("--camera-frame", default="camera_optical_frame",
                     help="camera frame name in the ROS snippets (default camera_optical_frame)")
    _add_common(rep)
    return parser


# --- commands -------------------------------------------------------------------------------------


def _print_transform_summary(out: _Printer, result: dict, elapsed: float, incremental: bool = False) -> None:
    T = result["T_base_cam"]
    out.info("T_base_cam (camera pose in the base frame; camera axes x right, y down, z forward):")
    for row in T["R"]:
        out.info("  R  [" + "  ".join(f"{x: .6f}" for x in row) + "]")
    out.info("  t  [" + "  ".join(f"{x: .5f}" for x in T["t"]) + "] m")
    out.info("  q_xyzw [" + "  ".join(f"{x: .6f}" for x in T["q_xyzw"]) + "]")
    sigma = result.get("sigma3_cam_base")
    if sigma:
        out.info("3-sigma bounds: rotation [" + ", ".join(f"{x:.3f}" for x in sigma["rotation_deg"]) + "] deg, "
                 "position [" + ", ".join(f"{x:.2f}" for x in sigma["position_mm"]) + "] mm (camera axes)")
    res = result["residuals"]
    unit = "px" if res.get("units", "px") == "px" else "(normalized)"
    opt = result["optimizer"]
    solver = "iSAM2 updates" if incremental else "LM iterations"
    out.info(f"residuals: RMS {res['rms_px']:.3f} {unit}, mean {res.get('mean_px', float('nan')):.3f}, "
             f"max {res['max_px']:.3f}; {solver} {opt['iterations']}"
             f"{'' if opt['converged'] else ' (NOT converged)'}; time {elapsed:.2f} s")
    expected = opt.get("expected_final_error")
    if expected and opt["final_error"] > expected + 10.0 * max(expected, 1.0) ** 0.5:
        out.info(f"warning: final cost {opt['final_error']:.4g} is far above its expected {expected:.4g} at the "
                 "optimum: a local minimum, outliers (try --robust) or a pixel_sigma that is too small")
    if res.get("outliers"):
        out.info(f"{len(res['outliers'])} measurement(s) above 5 sigma after the solve:")
        for o in res["outliers"][:20]:
            out.info(f"  image '{o['image']}' point '{o['point']}': {o['sigmas']:.1f} sigma")


def _load_any(path: Path, out: _Printer):
    """A Dataset from a dataset@1 file, or from a capture@1 file after detection."""
    from mirror_fg.dataset import dataset_from_dict, load_dataset

    if path.suffix.lower() in (".yaml", ".yml") or _looks_like_capture(path):
        from mirror_fg.capture import load_capture
        from mirror_fg.detect import detect_capture

        capture = load_capture(path)
        data, reports = detect_capture(capture, progress=out.progress)
        _print_detection_report(out, reports)
        return dataset_from_dict(data, source=str(path))
    return load_dataset(path)


def _looks_like_capture(path: Path) -> bool:
    import json

    try:
        with open(path, encoding="utf-8") as handle:
            return str(json.load(handle).get("format", "")).startswith("mirror-fg/capture@")
    except (OSError, ValueError, AttributeError):
        return False


def _print_detection_report(out: _Printer, reports) -> None:
    found = sum(1 for r in reports if r.status == "found")
    out.info(f"detection: target found in {found} of {len(reports)} image(s)")
    for r in reports:
        if r.status != "found":
            out.info("  " + r.line())
        else:
            out.detail("  " + r.line())


def cmd_simulate(args, out: _Printer) -> int:
    from mirror_fg.simulate import simulate_base_case, simulate_tree, write_simulation

    if args.tree:
        dataset, truth = simulate_tree(args.mirrors, num_fiducials=args.fiducials, num_points=args.points,
                                       pixel_sigma=args.sigma, seed=args.seed, mirror_distance=args.distance)
    else:
        dataset, truth = simulate_base_case(num_images=args.images, num_points=args.points, pixel_sigma=args.sigma,
                                            mirror_distance=args.distance, mirror1_placements=args.placements,
                                            seed=args.seed, num_mirrors=args.mirrors, num_fiducials=args.fiducials)
    write_simulation(args.output, dataset, truth)
    out.info(f"wrote {args.output} ({len(dataset.images)} images, {dataset.num_mirrors} mirror(s), "
             f"{len(dataset.fiducials)} fiducials, {len(dataset.reconstruction_point_names)} points) and its ground truth")
    return EXIT_OK


def cmd_calibrate(args, out: _Printer) -> int:
    from mirror_fg.dataset import DatasetError, write_result
    from mirror_fg.graph import calibrate

    start = time.perf_counter()
    if not args.no_ros:
        from mirror_fg.ros import check_frame_name

        try:
            check_frame_name(args.base_frame, "--base-frame")
            check_frame_name(args.camera_frame, "--camera-frame")
        except ValueError as error:
            raise DatasetError(str(error)) from None
    dataset = _load_any(args.input, out)
    if args.incremental:
        result = _run_incremental(dataset, args, out)
    else:
        bar = None
        if out.progress:
            from tqdm import tqdm

            bar = tqdm(desc="LM", unit=" it", file=sys.stderr, leave=False)

        def on_iteration(iteration: int, before: float, after: float) -> None:
            if bar is not None:
                bar.update(1)
                bar.set_postfix(error=f"{after:.4g}")

        try:
            calibration = calibrate(dataset, robust=args.robust, on_iteration=on_iteration)
        finally:
            if bar is not None:
                bar.close()
        if calibration.restarts:
            out.info(f"LM ended in a local minimum from the analytical solution; restarted from {calibration.restarts} "
                     "runner-up P3P hypothesis(es) and kept the lowest cost")
        if not calibration.converged:
            from mirror_fg.analytic import SolveError

            raise SolveError(f"{dataset.source}: Levenberg-Marquardt did not converge in {calibration.iterations} "
                             "iterations (stalled); the result was not written")
        result = calibration.to_dict()
    write_result(args.output, result)
    written = [str(args.output)]
    if not args.no_ros:
        from mirror_fg.ros import write_ros_outputs

        written += [str(p) for p in write_ros_outputs(result, args.output, args.base_frame, args.camera_frame)]
    _print_transform_summary(out, result, time.perf_counter() - start, args.incremental)
    out.info("wrote " + ", ".join(written))
    return EXIT_OK


def _run_incremental(dataset, args, out: _Printer) -> dict:
    from mirror_fg.incremental import IncrementalCalibrator

    calibrator = IncrementalCalibrator(dataset, robust=args.robust)
    calibration = None
    for index, image in enumerate(dataset.images, start=1):
        estimate = calibrator.add_image(image)
        if estimate is not None:
            calibration = estimate
            if index % max(args.every, 1) == 0 or index == len(dataset.images):
                s = estimate.to_dict()["sigma3_cam_base"]
                out.info(f"[{index:5d}/{len(dataset.images)}] 3-sigma rot [" + ", ".join(f"{x:.3f}" for x in s["rotation_deg"])
                         + "] deg, pos [" + ", ".join(f"{x:.1f}" for x in s["position_mm"]) + "] mm")
    if calibration is None:
        from mirror_fg.analytic import SolveError

        raise SolveError(f"{dataset.source}: the images never allowed an analytical solution "
                         "(each placement needs >= 3 child placements)")
    return calibrator.calibration(full=True).to_dict()


def cmd_detect(args, out: _Printer) -> int:
    from mirror_fg.capture import load_capture
    from mirror_fg.dataset import dataset_from_dict, save_dataset
    from mirror_fg.detect import detect_capture

    capture = load_capture(args.capture)
    data, reports = detect_capture(capture, progress=out.progress)
    _print_detection_report(out, reports)
    dataset = dataset_from_dict(data, source=str(args.capture))
    save_dataset(args.output, dataset)
    out.info(f"wrote {args.output} ({len(dataset.images)} images)")
    return EXIT_OK


def cmd_report(args, out: _Printer) -> int:
    from mirror_fg.dataset import DatasetError, load_dataset, load_result
    from mirror_fg.report import write_report

    result = load_result(args.result)
    dataset = load_dataset(args.dataset) if args.dataset is not None else None
    try:
        paths = write_report(result, dataset, args.output, progress=out.progress,
                             base_frame=args.base_frame, camera_frame=args.camera_frame)
    except ValueError as error:  # a malformed result file
        if isinstance(error, DatasetError):
            raise
        raise DatasetError(f"{args.result}: {error}") from None
    out.info("wrote " + ", ".join(str(p) for p in paths.values()))
    return EXIT_OK


def cmd_plan(args, out: _Printer) -> int:
    from mirror_fg.dataset import atomic_write
    from mirror_fg.plan import PlanSetup, format_plan, load_fiducials, plan

    fiducials = load_fiducials(args.fiducials_file) if args.fiducials_file is not None else None
    setup = PlanSetup(num_mirrors=args.mirrors, placements=args.placements, num_images=args.images,
                      num_fiducials=args.fiducials, fiducials=fiducials, num_points=args.points,
                      mirror_distance_m=args.distance, tilt_deg=args.tilt, pixel_sigma=args.sigma,
                      focal_px=args.focal)
    result = plan(setup, draws=args.draws, seed=args.seed)
    out.info(format_plan(result))
    if args.json is not None:
        import json

        atomic_write(args.json, json.dumps(result.to_dict(), indent=2))
        out.info(f"wrote {args.json}")
    return EXIT_OK


COMMANDS = {"plan": cmd_plan, "simulate": cmd_simulate, "calibrate": cmd_calibrate, "detect": cmd_detect, "report": cmd_report}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mirror-fg`` console script."""
    from mirror_fg.analytic import SolveError
    from mirror_fg.dataset import DatasetError

    args = build_parser().parse_args(argv)
    out = _Printer(args.quiet, args.verbose)
    np.set_printoptions(suppress=True)
    try:
        return COMMANDS[args.command](args, out)
    except DatasetError as error:
        print(f"mirror-fg: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SolveError as error:
        print(f"mirror-fg: cannot solve: {error}", file=sys.stderr)
        return EXIT_UNSOLVABLE
    except KeyboardInterrupt:
        print("mirror-fg: interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # noqa: BLE001 - the one place that turns bugs into one line
        if args.verbose:
            traceback.print_exc()
        print(f"mirror-fg: internal error: {type(error).__name__}: {error} (run with --verbose for details)",
              file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
