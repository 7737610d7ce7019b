"""``mirror-fg export RESULT --to FORMAT -o FILE``: a screen calibration in the file a gaze tool reads
(:mod:`mirror_fg.io.gaze_export`; docs/formats.md, "Gaze exports"). Parser setup and runner only."""
from __future__ import annotations

import argparse
from pathlib import Path

from mirror_fg.cli.printing import EXIT_OK, _Printer

__all__ = ["add_export_parser", "cmd_export"]


def add_export_parser(sub, epilog: str, add_common) -> None:  # noqa: ANN001 - argparse's sub-parsers action
    from mirror_fg.io.gaze_export import FORMATS

    exp = sub.add_parser("export", help="write a screen calibration in a gaze tool's file (OpenGaze, ETH-XGaze, few_shot_gaze)",
                         description="Write the screen-camera pose of a result@1 (from a capture with a screen target) "
                         "in the file a gaze tool reads: " + "; ".join(f"{k}: {v}" for k, v in FORMATS.items())
                         + ". docs/gaze_guide.md shows each.", epilog=epilog,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    exp.add_argument("result", type=Path, help="result@1 file with a 'screen' block")
    exp.add_argument("--to", required=True, choices=list(FORMATS), help="the tool's format")
    exp.add_argument("-o", "--output", required=True, type=Path, help="the file to write")
    exp.add_argument("--screen", metavar="NAME",
                     help="a result of several screens: the screen to write (default: the first, the top level)")
    exp.add_argument("--camera", type=Path,
                     help="few-shot-gaze: the camera's intrinsics (an OpenCV calibration YAML, ROS camera_info or "
                     "Kalibr camchain) where the result holds none")
    add_common(exp)


def cmd_export(args, out: _Printer) -> int:
    import os

    from mirror_fg.io.camera_files import camera_from_file
    from mirror_fg.io.gaze_export import MARKER, export_text, one_screen
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.io.result import load_result

    inputs = [os.fspath(args.result)] + ([os.fspath(args.camera)] if args.camera is not None else [])
    plan = OutputPlan(inputs=inputs)
    target = plan.add(args.output, f"{args.to} file", marker=MARKER.encode())
    result = load_result(args.result)
    if args.screen is not None:
        result = one_screen(result, args.screen, os.fspath(args.result))
    camera = camera_from_file(os.fspath(args.camera), None, f"--camera {args.camera}") if args.camera else None
    written = plan.commit({target: export_text(result, args.to, os.fspath(args.result), camera)})
    out.info(f"wrote {', '.join(str(p) for p in written)} ({args.to})")
    return EXIT_OK
