"""The CLI's reading of an input (dataset@1 or capture@1, detected with its report printed) and its
printing of a result's summary: shared by every command that calibrates, verifies or plans."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from mirror_fg.cli.printing import _Printer

if TYPE_CHECKING:
    from mirror_fg.data import Dataset
    from mirror_fg.io.output import OutputPlan

__all__ = ["print_transform_summary", "load_input_file", "load_input_with_reports", "detection_exclusions",
           "print_detection_report"]


def print_transform_summary(out: _Printer, result: dict, elapsed: float, incremental: bool = False,
                             pixel_sigma: float | None = None) -> None:
    """Each transform with its own bounds in its own frame, the residuals, the solver (report.summary)."""
    from mirror_fg.report.summary import summary_lines

    for line in summary_lines(result, verbose=out.verbose, incremental=incremental, pixel_sigma=pixel_sigma):
        out.info(line)
    out.info(f"time {elapsed:.2f} s")


def load_input_file(path: Path, out: _Printer, plan: OutputPlan, tracks: dict | None = None,
                capture_only: bool = False) -> Dataset:
    """A Dataset from a dataset@1 or capture@1 file (detected, with its report printed); read once."""
    return load_input_with_reports(path, out, plan, tracks, capture_only)[0]


def load_input_with_reports(path: Path, out: _Printer, plan: OutputPlan, tracks: dict | None = None,
                             capture_only: bool = False, on_capture: Any = None) -> tuple[Dataset, list]:
    """:func:`load_input_file` and the per-image detection reports (empty for a dataset@1)."""
    from mirror_fg.vision.detect import load_input

    dataset, reports = load_input(path, plan, progress=out.progress, tracks=tracks, capture_only=capture_only,
                                  on_capture=on_capture)
    if reports:
        print_detection_report(out, reports)
    return dataset, list(reports or [])


def detection_exclusions(reports: list) -> list:
    """Images of a capture that detection left out, as result@1 ``excluded`` entries (nothing dropped silently)."""
    from mirror_fg.solver.result.calibration import Exclusion
    from mirror_fg.vision.detectors import FOUND

    return [Exclusion(r.id, f"detection: {r.status}: {r.reason}") for r in reports if r.status != FOUND]


def print_detection_report(out: _Printer, reports) -> None:
    found = sum(1 for r in reports if r.status == "found")
    out.info(f"detection: target found in {found} of {len(reports)} image(s)")
    for r in reports:
        if r.status != "found":
            out.info("  " + r.line())
        else:
            out.detail("  " + r.line())
