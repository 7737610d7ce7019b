"""``mirror-fg verify RESULT DATA|CAPTURE``: has the camera moved since RESULT? (docs/formats.md, "Has it
moved?"). Its options (:func:`add_parser`) and its runner (:func:`cmd_verify`); the test is
``mirror_fg.analysis.verify``'s. Exit 0 not moved, 4 moved, 5 cannot tell, 2 bad input."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from mirror_fg.cli.printing import _Printer
from mirror_fg.registry.cli import add_registry_arguments

__all__ = ["add_parser", "cmd_verify"]


def add_parser(sub, common, epilog: str, positive) -> None:
    """The ``verify`` sub-parser (``common`` adds -q/-v; ``positive`` is the parser's finite-number type)."""
    ver = sub.add_parser("verify", help="has the camera moved? a few new images against a stored result",
                         description="Test, per camera, whether new images (a dataset@1 or a capture@1 with a few "
                         "mirror placements) agree with the transform and covariance RESULT stored: a likelihood-"
                         "ratio test with as many degrees of freedom as the new images determine. Exit 0 not moved, "
                         "4 moved, 5 cannot tell (with what to add).", epilog=epilog,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    ver.add_argument("result", type=Path, help="result@1 file of the stored calibration")
    ver.add_argument("data", type=Path, help="dataset@1 or capture@1 of the new images (same target and camera)")
    ver.add_argument("--alpha", type=_probability, default=0.01, help="false-alarm rate of 'moved' (default 0.01)")
    ver.add_argument("--tolerance-mm", type=positive, default=2.0,
                     help="'not moved' only if a move this large would have been seen (default 2 mm)")
    ver.add_argument("--tolerance-deg", type=positive, default=0.2,
                     help="'not moved' only if a rotation this large would have been seen (default 0.2 deg)")
    ver.add_argument("-o", "--output", type=Path, help="write the verification (verification@1 JSON) here")
    ver.add_argument("--update", type=Path, metavar="OUT",
                     help="where nothing moved: write the stored estimate combined with the new images (result@1)")
    ver.add_argument("--standing-mirror", action="store_true",
                     help="the new images' mirror placements that RESULT has (same mirror and config numbers) are the "
                     "same mirrors, standing where they stood: one placement then determines the camera")
    add_registry_arguments(ver)
    common(ver)


def _probability(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number between 0 and 1, got {text[:40]!r}")
    return value


def cmd_verify(args, out: _Printer) -> int:
    from mirror_fg.cli.loading import load_input_file
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.io.result import load_result, result_text
    from mirror_fg.io.verification import check_updatable, updated_result, verification_text
    from mirror_fg.registry.cli import record_document, registry_target
    from mirror_fg.analysis.verify import MOVED, verify

    target = registry_target(args)  # checked before any work
    plan = OutputPlan(inputs=[os.fspath(args.result), os.fspath(args.data)])
    if args.output is not None:
        plan.add(args.output, "verification")
    if args.update is not None:
        plan.add(args.update, "updated result")
    result = load_result(args.result)
    if args.update is not None:
        check_updatable(result, os.fspath(args.result))
    dataset = load_input_file(args.data, out, plan)
    verification = verify(result, dataset, alpha=args.alpha, tolerance_mm=args.tolerance_mm,
                          tolerance_deg=args.tolerance_deg, source=os.fspath(args.result),
                          standing=args.standing_mirror)
    contents = {}
    document = verification.to_dict(os.fspath(args.result), os.fspath(args.data))
    if args.output is not None:
        contents[os.fspath(args.output)] = verification_text(document)
    if args.update is not None and verification.verdict != MOVED:
        (fused,) = verification.fused.values()
        updated = updated_result(result, fused, os.fspath(args.result), os.fspath(args.data), len(dataset.images))
        contents[os.fspath(args.update)] = result_text(updated, args.update)
    if contents:
        plan.commit(contents)
    for line in verification_lines(verification):
        out.info(line)
    if args.output is not None:
        out.info(f"wrote {args.output}")
    if args.update is not None:
        out.info(f"wrote {args.update}" if verification.verdict != MOVED
                 else f"not written: {args.update} (a camera moved: calibrate again)")
    record_document(target, document, args.data, args.output, out)  # after the files: a failure costs none
    return verification.exit_code


def verification_lines(verification) -> list[str]:
    """Per camera: the verdict, p, the move with its 3-sigma, the detectable move, what to add."""
    lines = []
    for name, v in verification.cameras.items():
        lines.append(f"{name}: {v.verdict.upper()}  (p = {v.p_value:.3g}, d2 = {v.mahalanobis2:.2f}, "
                     f"{v.dof} of 6 degrees of freedom seen, alpha = {verification.alpha:g})")
        if v.move is not None and v.covariance is not None:
            sd3 = 3.0 * (v.covariance.diagonal().clip(0.0)) ** 0.5
            rot = ", ".join(f"{math.degrees(a):+.3f} ± {math.degrees(s):.3f}" for a, s in zip(v.move[:3], sd3[:3]))
            pos = ", ".join(f"{1e3 * a:+.2f} ± {1e3 * s:.2f}" for a, s in zip(v.move[3:], sd3[3:]))
            lines.append(f"  move (new - stored, camera axes, 3-sigma): rotation [{rot}] deg")
            lines.append(f"                                           position [{pos}] mm")
        if math.isfinite(v.detectable_rad):
            lines.append(f"  smallest move seen with power 0.9: {math.degrees(v.detectable_rad):.3g} deg, "
                         f"{1e3 * v.detectable_m:.3g} mm (tolerance {verification.tolerance_deg:g} deg, "
                         f"{verification.tolerance_mm:g} mm)")
        else:
            lines.append("  smallest move seen: none in every direction (some directions unseen)")
        if v.dispersion_dof is not None and math.isfinite(v.dispersion):
            lines.append(f"  the stored images agree to {v.dispersion:.3g}x their noise model's variance "
                         f"({v.dispersion_dof:.0f} degrees of freedom): bounds x{max(1.0, v.dispersion) ** 0.5:.3g}, "
                         "F-test")
        if v.advice:
            lines.append(f"  {v.advice}")
    return lines



def live_verifier(args, session, out: _Printer):
    """``live --verify RESULT``: the verifier of a live session (``live/verify.py``), or None without it."""
    if getattr(args, "verify", None) is None:
        return None
    from mirror_fg.core.errors import DatasetError
    from mirror_fg.io.result import load_result
    from mirror_fg.live.verify import LiveVerifier

    if args.output is not None:
        raise DatasetError("live: --verify tests the frames against RESULT and calibrates nothing: drop -o (or run "
                           "without --verify to calibrate)")
    return LiveVerifier(load_result(args.verify), session, source=os.fspath(args.verify))


def live_verify_frame(verifier, record, out: _Printer, quiet: bool) -> None:
    """After an added frame: the verdict of the placements so far, one line (none with ``quiet``)."""
    if verifier is None or record.status != "added":
        return
    answer = verifier.update()
    if quiet:
        return
    if answer is None:
        out.info(f"[frame {record.frame}] verify: waiting: {verifier.waiting}")
        return
    for v in answer.cameras.values():
        seen = (f"smallest move seen {math.degrees(v.detectable_rad):.3g} deg, {1e3 * v.detectable_m:.3g} mm"
                if math.isfinite(v.detectable_rad) else "some directions unseen")
        out.info(f"[frame {record.frame}] verify: {v.name}: {v.verdict} (p = {v.p_value:.3g}, {v.dof} of 6 seen; {seen})")


def live_verify_end(verifier, out: _Printer) -> int:
    """At the end of a ``live --verify`` session: the verdict's lines and its exit status (5 without a
    verdict: nothing could be tested)."""
    if verifier.last is None:
        out.info(f"verify: cannot tell: {verifier.waiting}")
        return 5
    for line in verification_lines(verifier.last):
        out.info(line)
    return verifier.last.exit_code
