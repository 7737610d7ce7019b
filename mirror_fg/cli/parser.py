"""The ``mirror-fg`` argument parser: every subcommand's options and their checks (exit 2, one line)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from mirror_fg.cli.export_cmd import add_export_parser
from mirror_fg.cli.history_cmd import add_history_parser
from mirror_fg.cli.robot_cmd import add_robot_arguments, add_robot_plan_arguments
from mirror_fg.factors.robust import KERNELS, ROBUST_K
from mirror_fg.registry.cli import add_registry_arguments

EPILOG = """exit status: 0 success, 2 bad input (the message names the file, image or point),
3 could not solve (degenerate data, no convergence), 1 internal error. Output files are written
all-or-nothing and never over an input; if standard output fails (a closed pipe, a full disk), the
files are still written, a warning goes to stderr and the exit status is that of the work.
frames: T_cam_base maps base points into the camera (Cp = R Bp + t, OpenCV camera axes:
x right, y down, z forward); T_base_cam is its inverse, the camera's pose on the robot."""


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


def _point(text: str) -> tuple[float, float, float]:
    """``X,Y,Z``, metres (``calibrate --at``)."""
    from mirror_fg.solver.result.point_error import parse_point

    try:
        return parse_point(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


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
                         "default) and, beside it, <name>.truth.json with the true unknowns. --kind kaleidoscope: "
                         "2 or 3 fixed mirrors, one image per view (direct, first- and second-order); --kind mixed: "
                         "two hand-held mirrors seen alone and both in either order; --cameras N: a rig of N "
                         "cameras with different intrinsics, some photographs shared by all of them.",
                         epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sim.add_argument("-o", "--output", required=True, type=Path, help="dataset file to write (JSON)")
    sim.add_argument("--kind", choices=["tree", "kaleidoscope", "mixed"], default="tree",
                     help="tree: the paper's nested mirrors (default); kaleidoscope: fixed mirrors around the "
                     "target; mixed: two hand-held mirrors in views of orders 1 and 2")
    sim.add_argument("--mirrors", type=_COUNT, help="number of mirrors Nv (default 2; a kaleidoscope 2 or 3)")
    sim.add_argument("--images", type=_COUNT, help="number of images (tree base case; default 200)")
    sim.add_argument("--points", type=_COUNT0,
                     help="reconstruction points (default 0; 1 with --no-target)")
    sim.add_argument("--sigma", type=_POSITIVE, default=1.0, help="pixel noise standard deviation, pixels (default 1.0)")
    sim.add_argument("--fiducials", type=int, choices=[3, 4], help="3 (paper) or 4 fiducials (tree kind)")
    sim.add_argument("--distance", type=_POSITIVE, help="camera-to-mirror distance, metres (tree kind; default 0.5)")
    sim.add_argument("--placements", metavar="N[,N2]",
                     help="tree: placements of mirror 1 (default 3); mixed: of mirror 1 and 2 (default 4,4; one "
                     "number for both)")
    sim.add_argument("--tree", action="store_true", help="minimal tree instead: 3 placements per node, 3^Nv images")
    sim.add_argument("--no-target", action="store_true",
                     help="kaleidoscope without fiducials: unknown points only, scale = mirror 1's distance")
    sim.add_argument("--direct", type=_COUNT0, help="mixed: photographs that also give the direct view (default 0)")
    sim.add_argument("--cameras", type=_number(int, 2), help="a rig of N >= 2 cameras (tree or mixed kind; with "
                     "--robot, N cameras beside each other on the arm's base, or on its tool with --eye-in-hand)")
    sim.add_argument("--shared", type=_COUNT0,
                     help="with --cameras: photographs every camera sees (default 8 tree, 2 mixed)")
    sim.add_argument("--own", metavar="N[,N...]",
                     help="with --cameras: photographs only each camera sees, one number for all or one per camera "
                     "(default 30 tree, 4 mixed)")
    sim.add_argument("--seed", type=_COUNT0, default=0, help="random seed (default 0)")
    add_robot_arguments(sim)
    _add_common(sim)

    cal = sub.add_parser("calibrate", help="analytical solution + MLE from a dataset or capture file",
                         description="Calibrate from a mirror-fg/dataset@1 (or a mirror-fg/capture@1, detected "
                         "first): analytical solution, Levenberg-Marquardt MLE, covariances. Writes a "
                         "mirror-fg/result@1 (JSON, or YAML when the name ends in .yaml) atomically, and beside "
                         "it <name>.ros.yaml and <name>.urdf.xml.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    cal.add_argument("input", type=Path, help="dataset@1 JSON or capture@1 YAML/JSON file")
    cal.add_argument("-o", "--output", required=True, type=Path, help="result file (.json or .yaml)")
    cal.add_argument("--robust", choices=KERNELS,
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
    cal.add_argument("--at", action="append", type=_point, default=[], metavar="X,Y,Z",
                     help="a point the camera measures (metres, camera frame, e.g. a grasp 0,0,0.6): its 3-sigma in the "
                     "base frame from T_base_cam's covariance, in the result ('at') and printed; repeatable")
    cal.add_argument("--validate", action="store_true",
                     help="hold each image out in turn (up to 200) and compare its residuals with what the others' "
                     "covariance predicts: ratio near 1 when the noise model and the bounds hold ('validation')")
    cal.add_argument("--viewing-distance", type=_POSITIVE, default=0.6, metavar="M",
                     help="screen targets: the eye's distance in front of the screen for the gaze-point error, "
                     "metres (default 0.6)")
    add_registry_arguments(cal)
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
    add_registry_arguments(many, per_input=True)
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
    pln.add_argument("--kind", choices=["tree", "kaleidoscope", "mixed"], default=None,
                     help="the set-up simulated (as mirror-fg simulate --kind; default the paper's tree)")
    pln.add_argument("--cameras", type=_number(int, 2), help="a rig of N >= 2 cameras: every camera's bounds and the "
                     "rig's (tree or mixed kind)")
    pln.add_argument("--shared", metavar="K[,K...]",
                     help="with --cameras: photographs every camera sees; several values compare them (e.g. 1,2,4,8)")
    pln.add_argument("--draws", type=_COUNT, default=5, help="random scenes averaged (default 5)")
    pln.add_argument("--seed", type=_COUNT0, default=0, help="random seed (default 0)")
    pln.add_argument("--json", type=Path, help="also write the bounds to this JSON file")
    pln.add_argument("--next", dest="next_data", type=Path, metavar="DATA|CAPTURE",
                     help="guided capture: calibrate these data and rank the mirror placements to try next by the "
                          "camera position's predicted 3-sigma")
    pln.add_argument("--result", type=Path, metavar="RESULT",
                     help="with --next: the result@1 of these data (its estimate is used; no new calibration)")
    pln.add_argument("--count", type=_COUNT, default=3, help="with --next: suggestions to print (default 3)")
    pln.add_argument("--max-tilt", type=_number(float, 0.0, 89.0, low_open=True),
                     help="with --next: largest reachable tilt of the mirror from the optical axis, degrees "
                          "(default: the largest used so far + 10, at most 60)")
    pln.add_argument("-o", "--output", type=Path, help="with --next: write the suggestions (suggestions@1 JSON) here")
    add_robot_plan_arguments(pln)
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
    liv.add_argument("--json-lines", type=Path,
                     help="one JSON object per frame (fields: docs/formats.md, 'Live sessions'); - for standard output")
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
    liv.add_argument("--verify", type=Path, metavar="RESULT", help="has it moved? test each new placement against RESULT")
    add_registry_arguments(liv)
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
    from mirror_fg.cli.verify_cmd import add_parser as add_verify

    add_verify(sub, _add_common, EPILOG, _POSITIVE)
    add_export_parser(sub, EPILOG, _add_common)
    add_history_parser(sub, _add_common)
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
