"""``mirror-fg history ROBOT [--camera NAME] [--registry URL] [-o history.html|history.csv]``: a robot's records
printed, and plotted or tabled (mirror_fg.registry.history; docs/formats.md#has-it-moved-mirror-fg-verify-and-the-calibration-registry)."""
from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path

from mirror_fg.cli.printing import EXIT_OK, _Printer
from mirror_fg.registry.cli import ENV_VAR

__all__ = ["add_history_parser", "cmd_history"]


def add_history_parser(sub: argparse._SubParsersAction, add_common: Callable[[argparse.ArgumentParser], None]) -> None:
    hist = sub.add_parser("history", help="a robot's calibrations and verifications from the registry",
                          description="List a robot's records in the calibration registry and flag every change "
                          "between consecutive calibrations of a camera beyond their combined 3-sigma; -o writes "
                          "the plots of each camera's position and rotation over time with 3-sigma bands and "
                          "verdicts (HTML) or the table (CSV).")
    hist.add_argument("robot", metavar="ROBOT", help="the robot ID the runs were recorded for (--robot)")
    hist.add_argument("--camera", metavar="NAME", help="only this camera (a single camera is named 'camera')")
    hist.add_argument("--registry", metavar="URL", help=f"sqlite:///path.db or postgresql://user@host:port/db "
                      f"(default: ${ENV_VAR})")
    hist.add_argument("-o", "--output", type=Path, help="history.html (plots) or history.csv (table)")
    add_common(hist)


def cmd_history(args, out: _Printer) -> int:
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.registry.history import flag_changes, history_csv, history_html, history_lines
    from mirror_fg.registry.schema import RegistryError, describe
    from mirror_fg.registry.store import Registry

    url = args.registry or os.environ.get(ENV_VAR)
    if not url:
        raise RegistryError(f"history needs a registry: --registry URL or ${ENV_VAR}")
    plan = OutputPlan(inputs=[])
    kind = None
    if args.output is not None:
        kind = args.output.suffix.lower()
        if kind not in (".html", ".htm", ".csv"):
            raise RegistryError(f"-o {args.output}: history writes .html (plots) or .csv (table)")
        plan.add(args.output, "history")
    with Registry(url) as registry:
        records = registry.history(args.robot, args.camera)
        if not records:
            robots = registry.robots()
            known = f" (robots there: {', '.join(robots[:10])}{' ...' if len(robots) > 10 else ''})" if robots else ""
            camera = f" camera {args.camera!r}:" if args.camera else ""
            raise RegistryError(f"robot {args.robot!r}:{camera} no records in {describe(url)}{known}")
    changes = flag_changes(records)
    for line in history_lines(args.robot, records, changes):
        out.info(line)
    if args.output is not None:
        text = (history_csv(records, changes) if kind == ".csv"
                else history_html(args.robot, records, changes, describe(url)))
        plan.commit({os.fspath(args.output): text})
        out.info(f"wrote {args.output}")
    return EXIT_OK
