"""The bench commands: ``plan --next`` (the next placement), ``live`` (a session while the mirror
moves) and ``pattern`` (a screen's pattern)."""
from __future__ import annotations

import os
import sys
from typing import Any

from mirror_fg.cli.loading import load_input_file, print_transform_summary
from mirror_fg.cli.printing import EXIT_OK, _Printer
from mirror_fg.core.errors import DatasetError


def plan_next(args, out: _Printer) -> int:
    """``plan --next``: calibrate the data so far, then rank the reachable placements (solver/information/suggest.py)."""
    import json
    from dataclasses import replace

    from mirror_fg.io.output import OutputPlan
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.result.calibration import require_converged
    from mirror_fg.solver.screen.consensus import without
    from mirror_fg.solver.model.graph import InitialEstimate
    from mirror_fg.solver.information.suggest import Reach, default_reach, estimate_from_result, require_suggestions, suggest_next

    outputs = OutputPlan(inputs=[os.fspath(p) for p in (args.next_data, args.result) if p is not None])
    if args.output is not None:
        outputs.add(args.output, "suggestions")
    dataset = load_input_file(args.next_data, out, outputs)
    if not dataset.is_tree:
        raise DatasetError(f"{dataset.source}: plan --next ranks the next placement of the paper's hand-held mirrors "
                           "(images with mirror_configs, one camera, a known target); these images give reflections, "
                           "cameras or no fiducials: `mirror-fg plan --kind kaleidoscope|mixed` or `--cameras N` gives "
                           "the bounds of such set-ups")
    estimate: InitialEstimate
    if args.result is not None:  # the estimate of a calibration already made
        from mirror_fg.io.result import load_result

        used, estimate = estimate_from_result(load_result(args.result), dataset, os.fspath(args.result))
    else:
        calibration = require_converged(calibrate(dataset), dataset.source)
        used = without(dataset, calibration.excluded) if calibration.excluded else dataset
        estimate = calibration
    reach = default_reach(used, estimate)
    if args.distance is not None:
        low, high = (args.distance[0] * 0.9, args.distance[0] * 1.1) if len(args.distance) == 1 else args.distance
        reach = Reach((low, high), reach.max_tilt_deg)
    if args.max_tilt is not None:
        reach = replace(reach, max_tilt_deg=args.max_tilt)
    suggestions = require_suggestions(suggest_next(used, estimate, count=args.count, reach=reach), dataset.source)
    if args.output is not None:
        outputs.commit({os.fspath(args.output): json.dumps(suggestions.to_dict(), indent=2)})
    out.info(suggestions.text())
    if args.output is not None:
        out.info(f"wrote {args.output}")
    return EXIT_OK


def cmd_live(args, out: _Printer) -> int:
    """``live``: the session loop of live/session.py between a frame source, the outputs and the page.

    Every output is checked against every input and each other before the first frame
    (live/save.py); ``--save`` writes each used frame as it is added. Ctrl-C, SIGTERM and SIGHUP
    end the session as the source's end does: the saved capture is finished and the result written."""
    import signal

    from mirror_fg.cli.verify_cmd import live_verifier, live_verify_end, live_verify_frame
    from mirror_fg.io.capture import capture_from_file_data
    from mirror_fg.io.fileio import load_structured
    from mirror_fg.registry.cli import record_document, registry_target
    from mirror_fg.solver.result.calibration import require_converged
    from mirror_fg.live.session import LiveSession, run
    from mirror_fg.live.save import SessionFolder, plan_live_outputs
    from mirror_fg.live.sources import open_source

    registry = registry_target(args)
    source_path = os.fspath(args.capture)
    data = load_structured(source_path, source_path)
    capture = capture_from_file_data(data, source_path, media=False)
    arm_files = ([capture.robot["path"], capture.robot["robot"]["urdf"]] if capture.robot is not None
                 and isinstance(capture.robot["robot"].get("urdf"), str) else [])  # an arm's joints CSV and URDF
    outputs = plan_live_outputs(source_path, args.source, [*capture.input_files(), *arm_files],
                                None if args.output is None else os.fspath(args.output),
                                None if args.json_lines is None else os.fspath(args.json_lines),
                                None if args.save is None else os.fspath(args.save), ros=not args.no_ros)
    folder: SessionFolder | None = None
    session: Any  # a LiveSession, or an arm's LiveArmSession (the same loop drives both)
    if capture.robot is not None:  # an arm: joint states from the capture's growing CSV (live/joints.py)
        from mirror_fg.live.joints import LiveArmSession

        session = LiveArmSession(capture, target_mm=args.target_mm, target_deg=args.target_deg,
                                 on_added=lambda frame, gray, image: folder.add(frame, gray, image)
                                 if folder is not None else None, picture=args.serve is not None)
    else:
        session = LiveSession(capture, target_mm=args.target_mm, target_deg=args.target_deg,
                              on_added=lambda frame, gray: folder.add(frame, gray) if folder is not None else None,
                              picture=args.serve is not None)
    verifier = live_verifier(args, session, out)
    if args.save is not None:
        folder = SessionFolder(os.fspath(args.save), data, session.camera_dict, robot=capture.robot)
    source = open_source(args.source, idle_s=args.idle)
    if capture.robot is not None:
        session.source = source  # each frame's name or time, matched to the joint states
    server = None
    if args.serve is not None:
        from mirror_fg.live.server import LiveServer

        server = LiveServer(args.serve, lambda: session.state)
        server.start()
        out.info(f"serving the live page on {server.url}")

    def on_record(record) -> None:
        live_verify_frame(verifier, record, out, quiet=outputs.stream is sys.stdout)
        if outputs.stream is not None:
            outputs.write_line(record.to_json())
        elif record.status == "added":
            bounds = ("" if record.sigma3_base_cam is None else " 3-sigma pos ["
                      + ", ".join(f"{x:.1f}" for x in record.sigma3_base_cam["position_mm"]) + "] mm")
            out.info(f"[frame {record.frame}] placement {record.placements} added{bounds}"
                     + (f"; {record.reason}" if record.reason else ""))

    interrupted = []

    def stop(signum, frame) -> None:  # noqa: ANN001 - a signal handler
        interrupted.append(signum)
        source.stop()

    caught = [s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None]
    previous = {signum: signal.signal(signum, stop) for signum in caught}
    written: list[str] = []
    try:
        outputs.open_lines()
        figures = run(session, source, on_record=on_record, stop_when_done=args.stop_when_done)
        out.info(f"{session.summary()}; {figures['fps']:.1f} frames/s, {figures['dropped']} dropped, "
                 f"{figures['unreadable']} unreadable")
        if interrupted:
            out.info(f"stopped by {signal.Signals(interrupted[0]).name}")
        if server is not None and args.hold and not interrupted:
            out.info(f"source ended; the page stays up on {server.url} until Ctrl-C")
            import threading

            held = threading.Event()
            for signum in caught:
                signal.signal(signum, lambda *a: held.set())
            while not held.wait(0.2):
                pass
    finally:
        if server is not None:
            server.stop()
        outputs.close_lines()
        try:
            if folder is not None:  # on any end, an error's too: the frames so far stay usable
                written += folder.finish()
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
    if session.done:
        out.info("done: every bound is below its target")
    if verifier is not None:
        if written:
            out.info(f"wrote {len(written)} file(s): " + ", ".join(written[-3:]) + (" ..." if len(written) > 3 else ""))
        return live_verify_end(verifier, out)
    calibration = require_converged(session.result(), capture.source)
    result = calibration.to_dict()
    if outputs.calibration is not None:
        written += [os.fspath(p) for p in outputs.calibration.write(result)]
    print_transform_summary(out, result, figures["seconds"], incremental=True)
    if written:
        out.info(f"wrote {len(written)} file(s): " + ", ".join(written[-3:]) + (" ..." if len(written) > 3 else ""))
    record_document(registry, result, source_path, args.output, out)
    return EXIT_OK


def cmd_pattern(args, out: _Printer) -> int:
    from mirror_fg.vision.pattern import pattern_summary, write_pattern

    screen, files = write_pattern(args.output, args.screen, args.screen_mm, args.diagonal, args.kind, args.square_mm)
    for line in pattern_summary(screen, files):
        out.info(line)
    return EXIT_OK
