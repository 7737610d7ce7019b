"""Command line: ``mirror-fg simulate | calibrate | calibrate-many | detect | plan | report | pattern``. Parsing
and printing only (the library decides; docs/formats.md says what goes in and out). Just over 500
lines: the seven subcommands' parsers and printers, nothing else.

Exit status: 0 success, 2 bad input, 3 could not solve (degenerate data, no convergence).
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mirror_fg.core.errors import DatasetError, MirrorFgError
from mirror_fg.factors.robust import ROBUST_K

if TYPE_CHECKING:
    from mirror_fg.io.dataset import Dataset
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.vision.tracking import Track

EXIT_OK, EXIT_INTERNAL = 0, 1  # bad input and unsolvable data: MirrorFgError.exit_code (2, 3)

EPILOG = """exit status: 0 success, 2 bad input (the message names the file, image or point),
3 could not solve (degenerate data, no convergence), 1 internal error. Output files are written
all-or-nothing and never over an input; if standard output fails (a closed pipe, a full disk), the
files are still written, a warning goes to stderr and the exit status is that of the work.
frames: T_cam_base maps base points into the camera (Cp = R Bp + t, OpenCV camera axes:
x right, y down, z forward); T_base_cam is its inverse, the camera's pose on the robot."""


class _Printer:
    """Human output on stdout. A failing stdout (closed pipe, full disk) is reported once on stderr and
    then ignored: it never changes the exit status or the files."""

    def __init__(self, quiet: bool, verbose: bool):
        self.quiet, self.verbose = quiet, verbose
        self.stdout_failed = False

    def info(self, text: str = "") -> None:
        if not self.quiet:
            self._print(text)

    def detail(self, text: str) -> None:
        if self.verbose and not self.quiet:
            self._print(text)

    def _print(self, text: str) -> None:
        if self.stdout_failed:
            return
        try:
            print(text, flush=True)
        except OSError as error:
            self.stdout_broken(error)

    def stdout_broken(self, error: OSError) -> None:
        """Stop printing; send what is left of stdout to /dev/null so the exit flush stays quiet."""
        self.stdout_failed = True
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError):
            pass
        try:
            print(f"mirror-fg: warning: standard output failed ({error.strerror or error}); output files are "
                  "not affected", file=sys.stderr, flush=True)
        except OSError:
            pass

    @property
    def progress(self) -> bool:
        return not self.quiet and sys.stderr.isatty()


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (exit 2) like every other bad input."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind: type, low: float, high: float = math.inf, low_open: bool = False):
    """An argparse type: a finite ``kind`` in [low, high] (``(low, high]`` with ``low_open``)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text[:40]!r}")
        if not math.isfinite(value) or value < low or (low_open and value == low) or value > high:
            bound = f"> {low:g}" if low_open else f">= {low:g}"
            if high < math.inf:
                bound += f" and <= {high:g}"
            raise argparse.ArgumentTypeError(f"must be a finite {'integer' if kind is int else 'number'} {bound}, "
                                             f"got {text[:40]!r}")
        return value

    parse.__name__ = kind.__name__
    return parse


_COUNT, _COUNT0, _POSITIVE = _number(int, 1), _number(int, 0), _number(float, 0.0, low_open=True)


def _distance_range(text: str) -> tuple[float, ...]:
    """``D`` or ``MIN,MAX`` (metres, positive, finite)."""
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in values) or values[0] > values[-1]:
        raise argparse.ArgumentTypeError(f"expected a distance in metres or MIN,MAX with 0 < MIN <= MAX, got {text!r}")
    return values


def _intrinsic_names(text: str) -> tuple[str, ...]:
    """An argparse type: comma-separated distinct intrinsic names (``camera.estimate``)."""
    from mirror_fg.core.camera import INTRINSIC_NAMES

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    for name in names:
        if name not in INTRINSIC_NAMES:
            raise argparse.ArgumentTypeError(f"unknown intrinsic {name[:20]!r} (one of {', '.join(INTRINSIC_NAMES)})")
    if not names or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"expected distinct names from {', '.join(INTRINSIC_NAMES)}, got {text[:60]!r}")
    return names


def _add_common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    group.add_argument("-v", "--verbose", action="store_true", help="print more detail (and tracebacks of internal errors)")


class _VersionAction(argparse.Action):
    """``--version``: the installed version, read (importlib.metadata) only when asked for."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # noqa: ANN001
        from mirror_fg import __version__

        print(f"mirror-fg {__version__}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="mirror-fg",
        description="Calibrate a camera to a robot base it sees only through planar mirrors "
        "(Hesch, Mourikis & Roumeliotis, ECCV 2010): analytical solution, GTSAM MLE, 3-sigma bounds.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=_VersionAction, nargs=0, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    sim = sub.add_parser("simulate", help="write a synthetic dataset and its ground truth",
                         description="Write a synthetic mirror-fg/dataset@1 (the paper's Sect. 7 base case by "
                         "default) and, beside it, <name>.truth.json with the true unknowns.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    sim.add_argument("-o", "--output", required=True, type=Path, help="dataset file to write (JSON)")
    sim.add_argument("--mirrors", type=_COUNT, default=2, help="number of mirrors Nv (default 2)")
    sim.add_argument("--images", type=_COUNT, default=200, help="number of images (base case; default 200)")
    sim.add_argument("--points", type=_COUNT0, default=0, help="reconstruction points near the fiducials (default 0)")
    sim.add_argument("--sigma", type=_POSITIVE, default=1.0, help="pixel noise standard deviation, pixels (default 1.0)")
    sim.add_argument("--fiducials", type=int, default=3, choices=[3, 4], help="3 (paper) or 4 fiducials")
    sim.add_argument("--distance", type=_POSITIVE, default=0.5, help="camera-to-mirror distance, metres (default 0.5)")
    sim.add_argument("--placements", type=_COUNT, default=3, help="placements of mirror 1 (default 3)")
    sim.add_argument("--tree", action="store_true", help="minimal tree instead: 3 placements per node, 3^Nv images")
    sim.add_argument("--seed", type=_COUNT0, default=0, help="random seed (default 0)")
    _add_common(sim)

    cal = sub.add_parser("calibrate", help="analytical solution + MLE from a dataset or capture file",
                         description="Calibrate from a mirror-fg/dataset@1 (or a mirror-fg/capture@1, detected "
                         "first): analytical solution, Levenberg-Marquardt MLE, covariances. Writes a "
                         "mirror-fg/result@1 (JSON, or YAML when the name ends in .yaml) atomically, and beside "
                         "it <name>.ros.yaml and <name>.urdf.xml.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    cal.add_argument("input", type=Path, help="dataset@1 JSON or capture@1 YAML/JSON file")
    cal.add_argument("-o", "--output", required=True, type=Path, help="result file (.json or .yaml)")
    cal.add_argument("--robust", choices=["huber", "cauchy"],
                     help=f"robust kernel on every measurement (threshold {ROBUST_K:g} sigma)")
    cal.add_argument("--incremental", action="store_true", help="iSAM2: stream the images in file order")
    cal.add_argument("--every", type=_COUNT, default=25, help="with --incremental: progress line every N images (default 25)")
    cal.add_argument("--base-frame", default="base_link", help="base frame name for the ROS outputs (default base_link)")
    cal.add_argument("--camera-frame", default="camera_optical_frame",
                     help="the camera's optical frame (OpenCV axes: x right, y down, z forward; default "
                     "camera_optical_frame); a *_link body-frame name is refused: the .ros.yaml also holds "
                     "camera_link's pose (x forward, REP 103)")
    cal.add_argument("--no-ros", action="store_true", help="do not write the ROS/URDF outputs beside the result")
    cal.add_argument("--accept-poor-fit", action="store_true",
                     help="write the result even when the fit is more than 3x worse than the noise model allows "
                     "(RMS whitened residual; refused by default: exit 3 with the likely causes)")
    _add_common(cal)

    many = sub.add_parser("calibrate-many", help="calibrate many datasets or captures (a fleet) on Dask",
                          description="Calibrate every input (dataset@1 or capture@1) into DIR/<stem>.result.json with "
                          "its ROS files, on a local Dask cluster (or --scheduler ADDRESS; a small job in this "
                          "process); prints a summary table. "
                          "One failure never stops the others; the exit status is 2 if any input failed.",
                          epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    many.add_argument("inputs", nargs="+", type=Path, help="dataset@1 or capture@1 files")
    many.add_argument("-o", "--output", required=True, type=Path, help="output directory")
    many.add_argument("--scheduler", metavar="ADDRESS",
                      help="a running Dask scheduler, tcp://HOST:PORT (default: a local cluster)")
    many.add_argument("--workers", type=_COUNT, default=2, help="local worker processes (default 2)")
    many.add_argument("--connect-timeout", type=_POSITIVE, default=10.0, metavar="SECONDS",
                      help="with --scheduler: give up if no Dask scheduler answers within SECONDS (default 10)")
    many.add_argument("--dask", action="store_true",
                      help="use a local Dask cluster even for a small job (default: a job of less than about "
                      "3 s of work runs in this process, which is faster than starting a cluster)")
    _add_common(many)

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
    pln.add_argument("--mirrors", type=_COUNT, help="number of mirrors Nv (default 2, or the capture's)")
    pln.add_argument("--placements", type=_number(int, 3), default=3,
                     help="placements of each mirror but the last per node (>= 3; default 3)")
    pln.add_argument("--images", type=_COUNT, default=200, help="number of images (default 200)")
    pln.add_argument("--fiducials", type=int, default=3, choices=[3, 4],
                     help="the paper's 20 cm right triangle (3) or with a point 15 cm off its plane (4)")
    pln.add_argument("--fiducials-file", type=Path,
                     help="JSON {name: [x, y, z]} base-frame fiducial layout, metres (overrides --fiducials)")
    pln.add_argument("--points", type=_COUNT0, default=0, help="reconstruction points within 10 cm of the fiducials")
    pln.add_argument("--distance", type=_distance_range, default=None,
                     help="camera-to-mirror distance, metres (default 0.5); with --next the reachable range MIN,MAX "
                          "(default: the distances used so far, widened by 10 %%)")
    pln.add_argument("--tilt", type=_number(float, 0.0, 89.0, low_open=True), default=30.0, help="largest mirror tilt, degrees (default 30)")
    pln.add_argument("--sigma", type=_POSITIVE, help="pixel noise standard deviation, pixels (default 1, or the capture's "
                                                     "pixel_sigma)")
    pln.add_argument("--focal", type=_POSITIVE, help="focal length, pixels (default: the camera's, else the simulator's 800)")
    given = pln.add_mutually_exclusive_group()
    given.add_argument("--camera", type=Path, metavar="FILE",
                       help="camera calibration file (OpenCV, ROS camera_info, Kalibr): its focal length")
    given.add_argument("--capture", type=Path, metavar="FILE",
                       help="capture@1 file: its camera (focal length, estimate), target (the fiducials, base frame), "
                            "pixel_sigma and num_mirrors; its images need not exist yet. Options given here win")
    pln.add_argument("--estimate", type=_intrinsic_names, default=(),
                     help="intrinsics estimated through the mirrors too, e.g. fx,fy,cx,cy,k1,k2: their bounds, and "
                          "the pose's with their uncertainty")
    pln.add_argument("--draws", type=_COUNT, default=5, help="random scenes averaged (default 5)")
    pln.add_argument("--seed", type=_COUNT0, default=0, help="random seed (default 0)")
    pln.add_argument("--json", type=Path, help="also write the bounds to this JSON file")
    pln.add_argument("--next", dest="next_data", type=Path, metavar="DATA|CAPTURE",
                     help="guided capture: calibrate these data and rank the mirror placements to try next by the "
                          "camera position's predicted 3-sigma")
    pln.add_argument("--count", type=_COUNT, default=3, help="with --next: suggestions to print (default 3)")
    pln.add_argument("--max-tilt", type=_number(float, 0.0, 89.0, low_open=True),
                     help="with --next: largest reachable tilt of the mirror from the optical axis, degrees "
                          "(default: the largest used so far + 10, at most 60)")
    pln.add_argument("-o", "--output", type=Path, help="with --next: write the suggestions (suggestions@1 JSON) here")
    _add_common(pln)

    liv = sub.add_parser("live", help="calibrate while the mirror is moved: camera, video or folder, with suggestions",
                         description="A session at the bench: each frame from --source is detected; a still frame showing a "
                         "new mirror placement is added to the incremental estimate, and the bounds and the next placement "
                         "to try are updated until every bound is below its target.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    liv.add_argument("capture", type=Path, help="capture@1 giving the camera, target, num_mirrors (1) and pixel_sigma")
    liv.add_argument("--source", required=True,
                     help="a camera index (0, 1, ...), a video file (read as fast as it is processed) or a folder "
                          "another program fills with images")
    liv.add_argument("-o", "--output", type=Path, help="result file written at the end (as calibrate writes it)")
    liv.add_argument("--json-lines", type=Path, help="one JSON object per frame (SPEC's fields); - for standard output")
    liv.add_argument("--serve", type=_number(int, 0, 65535), metavar="PORT",
                     help="a local web page on 127.0.0.1:PORT with the picture, the bounds and the suggestion (0: any free port)")
    liv.add_argument("--target-mm", type=_POSITIVE, help="done when every 3-sigma of the camera's position is below this")
    liv.add_argument("--target-deg", type=_POSITIVE, help="done when every 3-sigma of the camera's rotation is below this")
    liv.add_argument("--stop-when-done", action="store_true", help="stop as soon as the targets are met")
    liv.add_argument("--save", type=Path, metavar="DIR", help="write the frames used and a capture@1 that repeats the session")
    liv.add_argument("--idle", type=_POSITIVE, default=30.0,
                     help="a folder source ends after this many seconds without a new image (default 30)")
    liv.add_argument("--hold", action="store_true", help="with --serve: keep the page up after the source ends, until Ctrl-C")
    liv.add_argument("--no-ros", action="store_true", help="do not write the ROS files beside the result")
    _add_common(liv)

    rep = sub.add_parser("report", help="HTML + PDF report of a result",
                         description="Write report.html (self-contained) and report.pdf: summary, residuals, "
                         "3D scene, correlations.", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    rep.add_argument("result", type=Path, help="result@1 file")
    rep.add_argument("dataset", type=Path, nargs="?",
                     help="dataset@1 or capture@1 the result came from (enables residual plots; a capture's tracks too)")
    rep.add_argument("-o", "--output", required=True, type=Path, help="output directory")
    rep.add_argument("--base-frame", default="base_link", help="base frame name in the ROS snippets (default base_link)")
    rep.add_argument("--camera-frame", default="camera_optical_frame",
                     help="the camera's optical frame in the ROS snippets (default camera_optical_frame; "
                     "a *_link body-frame name is refused)")
    _add_common(rep)

    pat = sub.add_parser("pattern", help="draw a full-screen pattern to calibrate a webcam to its monitor (gaze)",
                         description="Draw a pattern of exactly the screen's pixels (ChArUco by default) to show full "
                         "screen and photograph in a hand-held mirror with the webcam; writes beside it "
                         "<name>.target.yaml (the capture@1 target, kind screen) and <name>.html (shows it at one image "
                         "pixel per device pixel, whatever the OS display scaling). docs/gaze_guide.md.",
                         epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    pat.add_argument("--screen", required=True, type=_size(int), metavar="WxH",
                     help="the screen's native resolution, pixels (e.g. 1920x1080)")
    size = pat.add_mutually_exclusive_group(required=True)
    size.add_argument("--screen-mm", type=_size(float), metavar="WxH",
                      help="the active area (the lit pixels), millimetres (e.g. 527x296.5)")
    size.add_argument("--diagonal", type=_POSITIVE, metavar="INCHES",
                      help="the diagonal, inches; with the aspect ratio of --screen (square pixels) it gives the size")
    pat.add_argument("--kind", choices=["charuco", "chessboard", "apriltag"], default="charuco",
                     help="charuco (default: survives partial views), chessboard (must be seen whole) or apriltag")
    pat.add_argument("--square-mm", type=_POSITIVE, help="square (tag spacing) on the screen, mm (default 40)")
    pat.add_argument("-o", "--output", required=True, type=Path, help="pattern PNG to write")
    _add_common(pat)
    return parser


def _size(kind: type):
    """An argparse type: ``WxH`` with two finite ``kind`` values >= 0 (0 is refused by the command, in words)."""
    def parse(text: str):
        parts = text.lower().replace("×", "x").split("x")
        try:
            values = tuple(kind(p) for p in parts)
        except ValueError:
            values = ()
        if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
            raise argparse.ArgumentTypeError(f"expected WxH ({'integers' if kind is int else 'numbers'} >= 0), "
                                             f"got {text[:40]!r}")
        return values

    parse.__name__ = "size"
    return parse


# --- commands -------------------------------------------------------------------------------------


def _print_transform_summary(out: _Printer, result: dict, elapsed: float, incremental: bool = False,
                             pixel_sigma: float | None = None) -> None:
    """Each transform with its own bounds in its own frame, the residuals, the solver (tools.summary)."""
    from mirror_fg.tools.summary import summary_lines

    for line in summary_lines(result, verbose=out.verbose, incremental=incremental, pixel_sigma=pixel_sigma):
        out.info(line)
    out.info(f"time {elapsed:.2f} s")


def _load_input(path: Path, out: _Printer, plan: OutputPlan, tracks: dict | None = None,
                capture_only: bool = False) -> Dataset:
    """A Dataset from a dataset@1 or capture@1 file (detected, with its report printed); read once."""
    return _load_input_with_reports(path, out, plan, tracks, capture_only)[0]


def _load_input_with_reports(path: Path, out: _Printer, plan: OutputPlan, tracks: dict | None = None,
                             capture_only: bool = False, on_capture: Any = None) -> tuple[Dataset, list]:
    """:func:`_load_input` and the per-image detection reports (empty for a dataset@1)."""
    from mirror_fg.vision.detect import load_input

    dataset, reports = load_input(path, plan, progress=out.progress, tracks=tracks, capture_only=capture_only,
                                  on_capture=on_capture)
    if reports:
        _print_detection_report(out, reports)
    return dataset, list(reports or [])


def _detection_exclusions(reports: list) -> list:
    """Images of a capture that detection left out, as result@1 ``excluded`` entries (nothing dropped silently)."""
    from mirror_fg.solver.calibration import Exclusion
    from mirror_fg.vision.detectors import FOUND

    return [Exclusion(r.id, f"detection: {r.status}: {r.reason}") for r in reports if r.status != FOUND]


def _print_detection_report(out: _Printer, reports) -> None:
    found = sum(1 for r in reports if r.status == "found")
    out.info(f"detection: target found in {found} of {len(reports)} image(s)")
    for r in reports:
        if r.status != "found":
            out.info("  " + r.line())
        else:
            out.detail("  " + r.line())


def cmd_simulate(args, out: _Printer) -> int:
    from mirror_fg.tools.simulate import simulate_base_case, simulate_tree, simulation_outputs, write_simulation

    plan = simulation_outputs(args.output)  # checked before the work
    if args.tree:
        dataset, truth = simulate_tree(args.mirrors, num_fiducials=args.fiducials, num_points=args.points,
                                       pixel_sigma=args.sigma, seed=args.seed, mirror_distance=args.distance)
    else:
        dataset, truth = simulate_base_case(num_images=args.images, num_points=args.points, pixel_sigma=args.sigma,
                                            mirror_distance=args.distance, mirror1_placements=args.placements,
                                            seed=args.seed, num_mirrors=args.mirrors, num_fiducials=args.fiducials)
    write_simulation(args.output, dataset, truth, plan)
    out.info(f"wrote {args.output} ({len(dataset.images)} images, {dataset.num_mirrors} mirror(s), "
             f"{len(dataset.fiducials)} fiducials, {len(dataset.reconstruction_point_names)} points) and its ground truth")
    return EXIT_OK


def cmd_calibrate(args, out: _Printer) -> int:
    from mirror_fg.io.calibration_files import plan_calibration_outputs
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.calibration import require_converged

    start = time.perf_counter()
    outputs = plan_calibration_outputs([args.input], args.output, ros=not args.no_ros,
                                       base_frame=args.base_frame, camera_frame=args.camera_frame)
    if not args.no_ros and not outputs.ros:
        out.info(f"note: the result goes to a device ({args.output}): no ROS outputs written beside it")
    dataset, reports = _load_input_with_reports(args.input, out, outputs.plan, on_capture=outputs.use_capture)
    if dataset.camera is not None and dataset.camera.estimate:
        if args.incremental:
            raise DatasetError(f"{dataset.source}: camera.estimate ({', '.join(dataset.camera.estimate)}): estimating "
                               "intrinsics needs the batch solver; drop --incremental")
        outputs.expect_camera()
    if args.incremental:
        calibration = _run_incremental(dataset, args, out)
    else:
        with _StageBars(out.progress) as bars:
            calibration = calibrate(dataset, robust=args.robust, progress=bars.update)
        if calibration.restarts:
            out.info(f"LM ended in a local minimum from the analytical solution; restarted from {calibration.restarts} "
                     "runner-up P3P hypothesis(es) and kept the lowest cost")
        require_converged(calibration, dataset.source, accept_poor_fit=args.accept_poor_fit)
    calibration.excluded = _detection_exclusions(reports) + list(calibration.excluded)
    result = calibration.to_dict()
    written = outputs.write(result)
    _print_transform_summary(out, result, time.perf_counter() - start, args.incremental,
                             pixel_sigma=None if dataset.point_sigma else dataset.pixel_sigma)
    if calibration.timings:
        out.detail("stage timings: " + ", ".join(f"{stage} {seconds:.3f} s" for stage, seconds in calibration.timings.items()))
    out.info("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


class _StageBars:
    """One progress bar per stage of ``calibrate`` (on stderr, when it is a terminal), named after it."""

    def __init__(self, show: bool):
        self.show = show
        self.stage: str | None = None
        self.bar: Any = None  # a tqdm bar while a stage runs

    def update(self, stage: str, done: int, total: int | None) -> None:
        if not self.show:
            return
        if stage != self.stage:
            self.close()
            from tqdm import tqdm

            self.stage = stage
            self.bar = tqdm(desc=stage, total=total, unit=" step", file=sys.stderr, leave=False)
        if self.bar is not None:
            self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> _StageBars:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def cmd_calibrate_many(args, out: _Printer) -> int:
    from mirror_fg.tools.many import calibrate_many

    rows = calibrate_many(args.inputs, args.output, scheduler=args.scheduler, workers=args.workers,
                          progress=out.progress, connect_timeout=args.connect_timeout,
                          in_process=False if args.dask else None)
    failed = [row for row in rows if row["status"] != "ok"]
    out.info(f"{len(rows) - len(failed)} of {len(rows)} calibrated into {args.output}")
    out.info("  camera position: 3-sigma of T_base_cam's translation along the base axes, mm; RMS: rms_px")
    out.info(f"  {'input':40s} {'status':7s} {'camera position':24s} {'RMS':>7s}  result or reason")
    for row in rows:
        if row["status"] == "ok":
            sigma = "[" + ", ".join(f"{x:.1f}" for x in row["sigma3_base_cam"]["position_mm"]) + "]"
            out.info(f"  {row['input'][-40:]:40s} {'ok':7s} {sigma:24s} {row['rms']:7.3f}  {row['result']}")
        else:
            out.info(f"  {row['input'][-40:]:40s} {'FAILED':7s} {'':24s} {'':>7s}  {_one_line(row['reason'])}")
    if failed:
        _error_line(f"mirror-fg: error: {len(failed)} of {len(rows)} input(s) failed (listed above)")
        return 2
    return EXIT_OK


def _run_incremental(dataset, args, out: _Printer):
    from mirror_fg.solver.incremental import calibrate_incremental

    total = len(dataset.images)

    def on_estimate(index: int, estimate) -> None:
        if index % args.every == 0 or index == total:
            s = estimate.to_dict()["sigma3_cam_base"]
            out.info(f"[{index:5d}/{total}] 3-sigma rot [" + ", ".join(f"{x:.3f}" for x in s["rotation_deg"])
                     + "] deg, pos [" + ", ".join(f"{x:.1f}" for x in s["position_mm"]) + "] mm")

    def on_wait(index: int, status: str) -> None:  # before start-up: what the calibrator waits for
        if index % args.every == 0 or index == total:
            out.info(f"[{index:5d}/{total}] {status}")

    return calibrate_incremental(dataset, robust=args.robust, on_estimate=on_estimate, on_wait=on_wait,
                                 accept_poor_fit=args.accept_poor_fit)


def cmd_detect(args, out: _Printer) -> int:
    from mirror_fg.io.dataset import dataset_text
    from mirror_fg.io.output import OutputPlan

    plan = OutputPlan(inputs=[os.fspath(args.capture)])
    plan.add(args.output, "dataset")
    dataset = _load_input(args.capture, out, plan, capture_only=True)
    _print_consensus(out, dataset)
    plan.commit({os.fspath(args.output): dataset_text(dataset)})
    out.info(f"wrote {args.output} ({len(dataset.images)} images)")
    return EXIT_OK


def _print_consensus(out: _Printer, dataset: Dataset) -> None:
    """What ``calibrate`` will leave out of a detected dataset, and why (``solver.consensus.screen``: each
    image's own PnP fit, the side of the board, agreement with the other placements of its mirror); the
    dataset itself keeps every detection."""
    from mirror_fg.solver.consensus import screen

    _, excluded, _ = screen(dataset)
    if excluded:
        out.info(f"check: calibrate will leave out {len(excluded)} image(s) or corner(s) that disagree with the rest:")
    for e in excluded:
        sigmas = f" ({e.sigmas:.1f} σ)" if e.sigmas is not None else ""
        out.info(f"  image '{e.image}'" + (f" point '{e.point}'" if e.point else "") + f": {e.reason}{sigmas}")


def cmd_report(args, out: _Printer) -> int:
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.io.result import load_result
    from mirror_fg.io.ros import check_camera_frame_name, check_frame_name
    from mirror_fg.tools.report import write_report

    plan = OutputPlan(inputs=[os.fspath(p) for p in (args.result, args.dataset) if p is not None])
    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise DatasetError(f"{args.output}: exists and is not a directory (report -o takes a directory)")
    for name in ("report.html", "report.pdf"):
        plan.add(Path(args.output) / name, "report")
    try:
        check_frame_name(args.base_frame, "--base-frame")
        check_camera_frame_name(args.camera_frame, "--camera-frame")
    except ValueError as error:
        raise DatasetError(str(error)) from None
    try:
        result = load_result(args.result)
    except DatasetError:
        _refuse_input_as_result(args)
        raise
    tracks: dict[str, Track] = {}
    dataset = None
    if args.dataset is not None:  # a dataset, or a capture (detected again: its tracks are drawn too)
        dataset = _load_input(args.dataset, out, plan, tracks=tracks)
    try:
        paths = write_report(result, dataset, args.output, progress=out.progress, source=os.fspath(args.result),
                             base_frame=args.base_frame, camera_frame=args.camera_frame, tracks=tracks or None)
    except ValueError as error:  # a malformed result file
        if isinstance(error, DatasetError):
            raise
        raise DatasetError(f"{args.result}: {error}") from None
    out.info("wrote " + ", ".join(str(p) for p in paths.values()))
    return EXIT_OK


def _refuse_input_as_result(args) -> None:
    """A dataset or capture given where ``report`` wants a result: say so, with the commands in their order."""
    from mirror_fg.io.capture import CAPTURE_FORMAT
    from mirror_fg.io.dataset import DATASET_FORMAT
    from mirror_fg.io.fileio import load_structured

    try:
        data = load_structured(args.result)
    except DatasetError:
        return
    kinds = {DATASET_FORMAT: "a dataset", CAPTURE_FORMAT: "a capture"}
    kind = kinds.get(str(data.get("format"))) if isinstance(data, dict) else None
    if kind is not None:
        then = ("the result comes first: mirror-fg report RESULT DATASET -o DIR" if args.dataset is not None else
                f"calibrate it first (mirror-fg calibrate {args.result} -o result.json), then mirror-fg report "
                f"result.json {args.result} -o {args.output}")
        raise DatasetError(f"{args.result}: is {kind}, not a result (mirror-fg/result@1); {then}")


def cmd_plan(args, out: _Printer) -> int:
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.tools.plan import PlanSetup, format_plan, load_fiducials, plan, setup_from_files

    if args.next_data is not None:
        return _plan_next(args, out)
    if args.output is not None or args.max_tilt is not None or (args.distance is not None and len(args.distance) > 1):
        raise DatasetError("plan: -o, --max-tilt and --distance MIN,MAX go with --next DATA (the bounds of a "
                           "described setup are written with --json)")
    outputs = OutputPlan(inputs=[os.fspath(p) for p in (args.fiducials_file, args.camera, args.capture) if p is not None])
    if args.json is not None:
        outputs.add(args.json, "plan JSON")
    given, taken = setup_from_files(camera=args.camera, capture=args.capture)
    fiducials = load_fiducials(args.fiducials_file) if args.fiducials_file is not None else given.get("fiducials")
    setup = PlanSetup(num_mirrors=args.mirrors or given.get("num_mirrors", 2), placements=args.placements,
                      num_images=args.images, num_fiducials=args.fiducials, fiducials=fiducials, num_points=args.points,
                      mirror_distance_m=0.5 if args.distance is None else args.distance[0], tilt_deg=args.tilt,
                      pixel_sigma=args.sigma or given.get("pixel_sigma", 1.0),
                      focal_px=args.focal or given.get("focal_px"), estimate=args.estimate or given.get("estimate", ()))
    if taken:
        out.info(taken)
    result = plan(setup, draws=args.draws, seed=args.seed)
    if args.json is not None:
        import json

        outputs.commit({os.fspath(args.json): json.dumps(result.to_dict(), indent=2)})
    out.info(format_plan(result))
    if args.json is not None:
        out.info(f"wrote {args.json}")
    return EXIT_OK


def _plan_next(args, out: _Printer) -> int:
    """``plan --next``: calibrate the data so far, then rank the reachable placements (tools/suggest.py)."""
    import json
    from dataclasses import replace

    from mirror_fg.io.output import OutputPlan
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.calibration import require_converged
    from mirror_fg.solver.consensus import without
    from mirror_fg.tools.suggest import Reach, default_reach, require_suggestions, suggest_next

    outputs = OutputPlan(inputs=[os.fspath(args.next_data)])
    if args.output is not None:
        outputs.add(args.output, "suggestions")
    dataset = _load_input(args.next_data, out, outputs)
    calibration = require_converged(calibrate(dataset), dataset.source)
    used = without(dataset, calibration.excluded) if calibration.excluded else dataset
    reach = default_reach(used, calibration)
    if args.distance is not None:
        low, high = (args.distance[0] * 0.9, args.distance[0] * 1.1) if len(args.distance) == 1 else args.distance
        reach = Reach((low, high), reach.max_tilt_deg)
    if args.max_tilt is not None:
        reach = replace(reach, max_tilt_deg=args.max_tilt)
    suggestions = require_suggestions(suggest_next(used, calibration, count=args.count, reach=reach), dataset.source)
    if args.output is not None:
        outputs.commit({os.fspath(args.output): json.dumps(suggestions.to_dict(), indent=2)})
    out.info(suggestions.text())
    if args.output is not None:
        out.info(f"wrote {args.output}")
    return EXIT_OK


def cmd_live(args, out: _Printer) -> int:
    """``live``: the session loop of tools/live.py between a frame source, the outputs and the page."""
    import signal

    from mirror_fg.io.calibration_files import plan_calibration_outputs
    from mirror_fg.io.capture import capture_from_file_data
    from mirror_fg.io.fileio import load_structured
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.solver.calibration import require_converged
    from mirror_fg.tools.live import LiveSession, run
    from mirror_fg.tools.live_sources import open_source

    source_path = os.fspath(args.capture)
    outputs = (plan_calibration_outputs([source_path], args.output, ros=not args.no_ros)
               if args.output is not None else None)
    streams = OutputPlan(inputs=[source_path])  # the JSON lines are checked like any output, then streamed
    if args.json_lines is not None and os.fspath(args.json_lines) != "-":
        streams.add(args.json_lines, "JSON lines")
    if args.save is not None and args.save.exists() and any(args.save.iterdir()):
        raise DatasetError(f"--save {args.save}: the folder exists and is not empty (nothing is written over)")
    data = load_structured(source_path, source_path)
    capture = capture_from_file_data(data, source_path, media=False)
    session = LiveSession(capture, target_mm=args.target_mm, target_deg=args.target_deg,
                          keep_frames=args.save is not None, picture=args.serve is not None)
    source = open_source(args.source, idle_s=args.idle)
    server = None
    if args.serve is not None:
        from mirror_fg.tools.live_server import LiveServer

        server = LiveServer(args.serve, lambda: session.state)
        server.start()
        out.info(f"serving the live page on {server.url}")
    lines = None
    if args.json_lines is not None:
        lines = sys.stdout if os.fspath(args.json_lines) == "-" else open(args.json_lines, "w")

    def on_record(record) -> None:
        if lines is not None:
            lines.write(record.to_json() + "\n")
            lines.flush()
        elif record.status == "added":
            bounds = ("" if record.sigma3_base_cam is None else " 3-sigma pos ["
                      + ", ".join(f"{x:.1f}" for x in record.sigma3_base_cam["position_mm"]) + "] mm")
            out.info(f"[frame {record.frame}] placement {record.placements} added{bounds}"
                     + (f"; {record.reason}" if record.reason else ""))

    interrupted = []

    def stop(signum, frame) -> None:  # noqa: ANN001 - a signal handler
        interrupted.append(signum)
        source.stop()

    previous = signal.signal(signal.SIGINT, stop)
    try:
        figures = run(session, source, on_record=on_record, stop_when_done=args.stop_when_done)
        out.info(f"{session.summary()}; {figures['fps']:.1f} frames/s, {figures['dropped']} dropped, "
                 f"{figures['unreadable']} unreadable")
        if server is not None and args.hold and not interrupted:
            out.info(f"source ended; the page stays up on {server.url} until Ctrl-C")
            import threading

            held = threading.Event()
            signal.signal(signal.SIGINT, lambda *a: held.set())
            while not held.wait(0.2):
                pass
    finally:
        signal.signal(signal.SIGINT, previous)
        if server is not None:
            server.stop()
        if lines is not None and lines is not sys.stdout:
            lines.close()
    if session.done:
        out.info("done: every bound is below its target")
    written = []
    if args.save is not None:
        written += session.save(os.fspath(args.save), data)
    calibration = require_converged(session.result(), capture.source)
    result = calibration.to_dict()
    if outputs is not None:
        written += [os.fspath(p) for p in outputs.write(result)]
    _print_transform_summary(out, result, figures["seconds"], incremental=True)
    if written:
        out.info(f"wrote {len(written)} file(s): " + ", ".join(written[-3:]) + (" ..." if len(written) > 3 else ""))
    return EXIT_OK


def cmd_pattern(args, out: _Printer) -> int:
    from mirror_fg.tools.pattern import pattern_summary, write_pattern

    screen, files = write_pattern(args.output, args.screen, args.screen_mm, args.diagonal, args.kind, args.square_mm)
    for line in pattern_summary(screen, files):
        out.info(line)
    return EXIT_OK


COMMANDS = {"live": cmd_live, "pattern": cmd_pattern, "plan": cmd_plan, "simulate": cmd_simulate,
            "calibrate": cmd_calibrate, "calibrate-many": cmd_calibrate_many, "detect": cmd_detect, "report": cmd_report}


#: Longest run of user data (a path, a value) quoted in an error line.
_MAX_QUOTE = 80


def _one_line(message: str) -> str:
    """``message`` on one line, any run of more than _MAX_QUOTE non-blank characters elided in the middle."""
    def elide(match: re.Match[str]) -> str:
        word = match.group(0)
        half = (_MAX_QUOTE - 3) // 2
        return word[:half] + "..." + word[-half:]

    return re.sub(r"\S{%d,}" % (_MAX_QUOTE + 1), elide, " ".join(str(message).split()))


class _Notes(logging.Handler):
    """Library INFO lines the user sees without ``-v`` (on stdout, like the other notes; -v shows them on stderr)."""

    def __init__(self, out: _Printer) -> None:
        super().__init__(logging.INFO)
        self.out = out

    def emit(self, record: logging.LogRecord) -> None:
        if not self.out.verbose:
            self.out.info("note: " + _one_line(record.getMessage()))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mirror-fg`` console script."""
    args = build_parser().parse_args(argv)
    out = _Printer(args.quiet, args.verbose)
    import numpy as np  # after parsing: --version and --help need none of the numerics

    np.set_printoptions(suppress=True)
    logger, handler = logging.getLogger("mirror_fg"), None
    level = logger.level
    if args.verbose:  # the library's messages (detection per image, solver stages) as they happen
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
    notes = _Notes(out)  # the camera a camchain gave: printed without -v too (issue 27)
    notes_logger = logging.getLogger("mirror_fg.io.camera_files")
    notes_logger.addHandler(notes)
    notes_level = notes_logger.level
    notes_logger.setLevel(logging.INFO)
    try:
        status = _run(args, out)
    finally:
        notes_logger.removeHandler(notes)
        notes_logger.setLevel(notes_level)
        if handler is not None:
            logger.removeHandler(handler)
            logger.setLevel(level)
    try:
        sys.stdout.flush()
    except OSError as error:
        out.stdout_broken(error)
    return status


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """A library warning (e.g. intrinsics weakly determined) as one line on stderr, without source lines."""
    _error_line(f"mirror-fg: warning: {_one_line(str(message))}")


def _run(args, out: _Printer) -> int:
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line
            return COMMANDS[args.command](args, out)
    except MirrorFgError as error:  # bad input (2) or cannot solve (3): one line
        _error_line(f"mirror-fg: {error.label}: {_one_line(str(error))}")
        return error.exit_code
    except KeyboardInterrupt:
        _error_line("mirror-fg: interrupted")
        return 130
    except Exception as error:  # noqa: BLE001 - the one place that turns bugs into one line
        if args.verbose:
            traceback.print_exc()
        _error_line(f"mirror-fg: internal error: {type(error).__name__}: {_one_line(str(error))} "
                    "(run with --verbose for details)")
        return EXIT_INTERNAL


def _error_line(text: str) -> None:
    try:
        print(text, file=sys.stderr, flush=True)
    except OSError:
        pass


if __name__ == "__main__":
    sys.exit(main())
