"""The calibration commands: simulate, calibrate, calibrate-many, detect, report, plan (argument
values in, the library's answer printed; the library decides)."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mirror_fg.core.errors import DatasetError

if TYPE_CHECKING:
    from mirror_fg.data import Dataset
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.vision.tracking import Track

from mirror_fg.cli.loading import (
    detection_exclusions,
    load_input_file,
    load_input_with_reports,
    print_transform_summary,
)
from mirror_fg.cli.printing import EXIT_OK, _error_line, _one_line, _Printer


def cmd_simulate(args, out: _Printer) -> int:
    from mirror_fg.simulate.tree import simulation_outputs

    if getattr(args, "robot", None) is not None:  # a robot arm (cli/robot_cmd.py)
        from mirror_fg.cli.robot_cmd import simulate_robot
        return simulate_robot(args, out)
    _check_simulate_options(args)
    plan = simulation_outputs(args.output)  # checked before the work
    if args.kind == "tree" and args.cameras is None:
        return _simulate_tree(args, out, plan)
    from mirror_fg.simulate.rig import simulate_rig_mixed, simulate_rig_tree
    from mirror_fg.simulate.views import simulate_kaleidoscope, simulate_mixed, write_views_simulation

    own = None if args.own is None else _simulate_counts(args.own, "--own", args.cameras)
    try:
        if args.kind == "kaleidoscope":
            dataset, truth = simulate_kaleidoscope(args.mirrors or 2, target=not args.no_target, num_points=args.points,
                                                   pixel_sigma=args.sigma, seed=args.seed)
        elif args.cameras is None:  # mixed
            placement_counts = _simulate_counts(args.placements or "4", "--placements", 2)
            dataset, truth = simulate_mixed(placement_counts, direct=args.direct or 0, num_points=args.points or 0,
                                            pixel_sigma=args.sigma, seed=args.seed)
        elif args.kind == "mixed":
            dataset, truth = simulate_rig_mixed(args.cameras, own=own, shared=2 if args.shared is None else args.shared,
                                                direct=args.direct or 0, num_points=args.points or 0,
                                                pixel_sigma=args.sigma, seed=args.seed)
        else:
            placements = _simulate_counts(args.placements or "3", "--placements", 1)[0]
            dataset, truth = simulate_rig_tree(args.cameras, own=own, shared=8 if args.shared is None else args.shared,
                                               placements=placements, num_mirrors=args.mirrors or 2,
                                               num_fiducials=args.fiducials or 3, num_points=args.points or 0,
                                               pixel_sigma=args.sigma, mirror_distance=args.distance or 0.5,
                                               seed=args.seed)
    except (ValueError, RuntimeError) as error:
        raise DatasetError(f"simulate: {str(error).removeprefix('simulate: ')}") from None
    write_views_simulation(args.output, dataset, truth, plan)
    orders = sorted({len(image.get("reflections", image.get("mirror_configs", []))) for image in dataset["images"]})
    cameras = f", {len(dataset['cameras'])} cameras" if "cameras" in dataset else ""
    out.info(f"wrote {args.output} ({len(dataset['images'])} images{cameras}, {dataset['num_mirrors']} mirror(s), "
             f"reflection orders {', '.join(map(str, orders))}, {len(dataset['fiducials'])} fiducials, "
             f"{len(truth.points)} points) and its ground truth")
    return EXIT_OK


def _simulate_tree(args, out: _Printer, plan: OutputPlan) -> int:
    """The paper's tree (the base case, or ``--tree``) for one camera."""
    from mirror_fg.simulate.tree import simulate_base_case, simulate_tree, write_simulation

    mirrors, fiducials, points = args.mirrors or 2, args.fiducials or 3, args.points or 0
    distance = args.distance or 0.5
    placements = _simulate_counts(args.placements or "3", "--placements", 1)[0]
    try:
        if args.tree:
            dataset, truth = simulate_tree(mirrors, num_fiducials=fiducials, num_points=points,
                                           pixel_sigma=args.sigma, seed=args.seed, mirror_distance=distance)
        else:
            dataset, truth = simulate_base_case(num_images=args.images or 200, num_points=points, pixel_sigma=args.sigma,
                                                mirror_distance=distance, mirror1_placements=placements,
                                                seed=args.seed, num_mirrors=mirrors, num_fiducials=fiducials)
    except ValueError as error:
        raise DatasetError(f"simulate: {error}") from None
    write_simulation(args.output, dataset, truth, plan)
    out.info(f"wrote {args.output} ({len(dataset.images)} images, {dataset.num_mirrors} mirror(s), "
             f"{len(dataset.fiducials)} fiducials, {len(dataset.reconstruction_point_names)} points) and its ground truth")
    return EXIT_OK


def _check_simulate_options(args) -> None:
    """One line (exit 2) for options that do not go with ``--kind`` / ``--cameras``."""
    kind, rig = args.kind, args.cameras is not None
    allowed = {  # option -> where it applies
        "--tree": kind == "tree" and not rig, "--images": kind == "tree" and not rig,
        "--no-target": kind == "kaleidoscope", "--direct": kind == "mixed",
        "--fiducials": kind == "tree", "--distance": kind == "tree",
        "--placements": kind == "tree" or (kind == "mixed" and not rig),
        "--shared": rig, "--own": rig, "--cameras": kind != "kaleidoscope",
    }
    given = {"--tree": args.tree, "--images": args.images is not None, "--no-target": args.no_target,
             "--direct": args.direct is not None, "--fiducials": args.fiducials is not None,
             "--distance": args.distance is not None, "--placements": args.placements is not None,
             "--shared": args.shared is not None, "--own": args.own is not None, "--cameras": rig}
    for option, used in given.items():
        if used and not allowed[option]:
            if option in ("--shared", "--own"):
                raise DatasetError(f"simulate: {option} goes with --cameras N (a rig)")
            where = f"--kind {kind}" + (" with --cameras" if rig and option != "--cameras" else "")
            raise DatasetError(f"simulate: {option} does not go with {where} (see mirror-fg simulate --help)")
    if kind == "kaleidoscope" and args.mirrors not in (None, 2, 3):
        raise DatasetError(f"simulate: a kaleidoscope has 2 or 3 mirrors, got --mirrors {args.mirrors}")
    if kind == "mixed" and args.mirrors not in (None, 2):
        raise DatasetError(f"simulate: --kind mixed simulates two hand-held mirrors, got --mirrors {args.mirrors}")
    if kind == "tree" and rig and args.mirrors not in (None, 1, 2):
        raise DatasetError(f"simulate: a simulated rig sees one or two mirrors, got --mirrors {args.mirrors}")


def _simulate_counts(text: str, option: str, count: int) -> list[int]:
    """``N`` (for all ``count``) or ``N1,...,Ncount``, each a whole number >= 0 (>= 1 for placements)."""
    parts = [p.strip() for p in text.split(",")]
    low = 1 if option == "--placements" else 0
    if not all(p.isdigit() and int(p) >= low for p in parts) or len(parts) not in (1, count):
        expect = "N" if count == 1 else f"N or {count} numbers N1,...,N{count}"
        raise DatasetError(f"simulate: {option} takes {expect} (whole numbers >= {low}), got {text[:40]!r}")
    return [int(parts[0])] * count if len(parts) == 1 else [int(p) for p in parts]


def cmd_calibrate(args, out: _Printer) -> int:
    from mirror_fg.cli.screens_cmd import calibrate_screens_input
    from mirror_fg.io.calibration_files import plan_calibration_outputs
    from mirror_fg.registry.cli import record_document, registry_target
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.result.calibration import require_converged
    from mirror_fg.report.verdict import with_verdict

    status = calibrate_screens_input(args, out)  # a capture with several screens (docs/formats.md)
    if status is not None:
        return status
    start = time.perf_counter()
    registry = registry_target(args)
    outputs = plan_calibration_outputs([args.input], args.output, ros=not args.no_ros,
                                       base_frame=args.base_frame, camera_frame=args.camera_frame)
    if not args.no_ros and not outputs.ros:
        out.info(f"note: the result goes to a device ({args.output}): no ROS outputs written beside it")
    outputs.viewing_distance_m = args.viewing_distance
    dataset, reports = load_input_with_reports(args.input, out, outputs.plan, on_capture=outputs.use_capture)
    estimating = [c for c in (list(dataset.cameras.values()) if dataset.cameras else [dataset.camera]) if c is not None and c.estimate]
    if dataset.robot is not None and args.incremental:  # a robot arm: the batch solver only
        raise DatasetError(f"{dataset.source}: robot: a robot arm's data need the batch solver; drop --incremental")
    if estimating and args.incremental:
        raise DatasetError(f"{dataset.source}: camera.estimate ({', '.join(estimating[0].estimate)}): estimating "
                           "intrinsics needs the batch solver; drop --incremental")
    if dataset.camera is not None and dataset.camera.estimate:
        outputs.expect_camera()
    if dataset.cameras is not None:
        outputs.expect_cameras()  # the camchain files, checked before the solve
    if args.incremental:
        calibration = _run_incremental(dataset, args, out)
    else:
        with _StageBars(out.progress) as bars:
            calibration = calibrate(dataset, robust=args.robust, progress=bars.update)
        if calibration.restarts:
            out.info(f"LM ended in a local minimum from the analytical solution; restarted from {calibration.restarts} "
                     "runner-up P3P hypothesis(es) and kept the lowest cost")
        require_converged(calibration, dataset.source, accept_poor_fit=args.accept_poor_fit)
    if getattr(args, "validate", False):  # before the detection exclusions: those images are not in the dataset
        from mirror_fg.solver.fit.validation import validate_calibration

        calibration.validation = validate_calibration(dataset, calibration)
    calibration.at_points = list(getattr(args, "at", None) or [])
    calibration.excluded = detection_exclusions(reports) + list(calibration.excluded)
    result = with_verdict(calibration.to_dict(), dataset)  # the one verdict: printed, stored, the report's
    written = outputs.write(result)
    print_transform_summary(out, result, time.perf_counter() - start, args.incremental,
                             pixel_sigma=None if dataset.point_sigma else dataset.pixel_sigma)
    if outputs.screen is not None:  # the gaze point's error (docs/formats.md, "The answer in the user's units")
        from mirror_fg.core.gaze_error import gaze_summary_lines
        from mirror_fg.io.screen_result import screen_block

        for line in gaze_summary_lines(screen_block(outputs.screen, result, args.viewing_distance)):
            out.info(line)
    if calibration.timings:
        out.detail("stage timings: " + ", ".join(f"{stage} {seconds:.3f} s" for stage, seconds in calibration.timings.items()))
    out.info("wrote " + ", ".join(str(p) for p in written))
    for note in outputs.notes:  # side files left out or removed (io.calibration_files)
        out.info(note)
    record_document(registry, result, args.input, args.output, out)
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
    from mirror_fg.registry.cli import registry_target
    from mirror_fg.analysis.many import calibrate_many

    registry = registry_target(args, per_input=True)
    rows = calibrate_many(args.inputs, args.output, scheduler=args.scheduler, workers=args.workers,
                          progress=out.progress, connect_timeout=args.connect_timeout,
                          in_process=False if args.dask else None, registry=registry)
    failed = [row for row in rows if row["status"] != "ok"]
    out.info(f"{len(rows) - len(failed)} of {len(rows)} calibrated into {args.output}")
    out.info("  camera position: 3-sigma of T_base_cam's translation along the base axes, mm; RMS: rms_px")
    out.info(f"  {'input':40s} {'status':7s} {'camera position':25s} {'RMS':>7s}  result or reason")
    for row in rows:
        if row["status"] == "ok":
            sigma = ("base = camera (no target)" if row.get("base_is_camera") else
                     "[" + ", ".join(f"{x:.1f}" for x in row["sigma3_base_cam"]["position_mm"]) + "]")
            out.info(f"  {row['input'][-40:]:40s} {'ok':7s} {sigma:25s} {row['rms']:7.3f}  {row['result']}")
        else:
            out.info(f"  {row['input'][-40:]:40s} {'FAILED':7s} {'':25s} {'':>7s}  {_one_line(row['reason'])}")
    if failed:
        _error_line(f"mirror-fg: error: {len(failed)} of {len(rows)} input(s) failed (listed above)")
        return 2
    return _registry_status(registry, rows, out)


def _registry_status(registry, rows: list[dict], out: _Printer) -> int:
    """calibrate-many's records (stored by each input's worker): a note, or exit 2 naming what was not stored."""
    if registry is None:
        return EXIT_OK
    lost = [row for row in rows if row.get("registry_error")]
    if lost:
        _error_line(f"mirror-fg: error: {len(lost)} of {len(rows)} record(s) not stored (the result files are "
                    f"written): {_one_line(lost[0]['registry_error'])}")
        return 2
    out.info(f"recorded {len(rows)} run(s) in the registry")
    return EXIT_OK


def _run_incremental(dataset, args, out: _Printer):
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

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
    dataset = load_input_file(args.capture, out, plan, capture_only=True)
    _print_consensus(out, dataset)
    plan.commit({os.fspath(args.output): dataset_text(dataset)})
    out.info(f"wrote {args.output} ({len(dataset.images)} images)")
    return EXIT_OK


def _print_consensus(out: _Printer, dataset: Dataset) -> None:
    """What ``calibrate`` will leave out of a detected dataset, and why (``solver.screen.consensus.screen``: each
    image's own PnP fit, the side of the board, agreement with the other placements of its mirror); the
    dataset itself keeps every detection."""
    from mirror_fg.solver.screen.consensus import screen

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
    from mirror_fg.report.writer import write_report

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
        dataset = load_input_file(args.dataset, out, plan, tracks=tracks)
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


def _plan_views(args, out: _Printer) -> int:
    """``plan --kind kaleidoscope|mixed`` and ``plan --cameras N [--shared K,...]`` (analysis/plan_views.py)."""
    import json

    from mirror_fg.io.output import OutputPlan
    from mirror_fg.analysis.plan_views import format_views_plan, plan_views

    if args.shared is not None and args.cameras is None:
        raise DatasetError("plan: --shared goes with --cameras N")
    kind = args.kind or "tree"
    if args.cameras is not None and kind == "kaleidoscope":
        raise DatasetError("plan: --cameras takes the tree or mixed kind")
    try:
        shared = [None] if args.shared is None else [int(k) for k in str(args.shared).split(",")]
    except ValueError:
        raise DatasetError(f"plan: --shared must be counts such as 1,2,4, got {args.shared!r}") from None
    if any(k is not None and k < 0 for k in shared):
        raise DatasetError("plan: --shared counts must be >= 0")
    outputs = OutputPlan(inputs=[])
    if args.json is not None:
        outputs.add(args.json, "plan JSON")
    results = []
    for k in shared:
        options = {} if k is None else {"shared": k}
        if kind == "kaleidoscope" and args.mirrors is not None:
            options["num_mirrors"] = args.mirrors
        try:
            result = plan_views(kind, args.cameras or 1, draws=args.draws, seed=args.seed,
                                pixel_sigma=args.sigma or 1.0, **options)
        except ValueError as error:  # the simulator's refusal: a camera that cannot be solved, ...
            raise DatasetError(f"plan: {error}") from None
        results.append(result)
        out.info(format_views_plan(result))
    if args.json is not None:
        outputs.commit({os.fspath(args.json): json.dumps([r.to_dict() for r in results], indent=2)})
        out.info(f"wrote {args.json}")
    return EXIT_OK


def cmd_plan(args, out: _Printer) -> int:
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.analysis.plan import PlanSetup, format_plan, load_fiducials, plan, setup_from_files

    if getattr(args, "robot", None) is not None or getattr(args, "joint_candidates", None) is not None:  # an arm
        from mirror_fg.cli.robot_cmd import plan_robot
        return plan_robot(args, out)
    if args.next_data is not None:
        from mirror_fg.cli.bench import plan_next  # the bench commands build on these

        return plan_next(args, out)
    if args.cameras is not None or args.kind in ("kaleidoscope", "mixed") or args.shared is not None:
        return _plan_views(args, out)
    if (args.output is not None or args.max_tilt is not None or args.result is not None
            or (args.distance is not None and len(args.distance) > 1)):
        raise DatasetError("plan: -o, --result, --max-tilt and --distance MIN,MAX go with --next DATA (the bounds of a "
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
