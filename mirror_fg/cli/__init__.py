"""Command line: ``mirror-fg simulate | calibrate | calibrate-many | detect | plan | report | live | pattern``.
Parsing and printing only (the library decides; docs/formats.md says what goes in and out):
``parser.py`` the options, ``commands.py`` the calibration commands, ``bench.py`` plan --next, live and
pattern, ``printing.py`` stdout and the one-line errors. ``main`` here runs one command and turns every
failure into one line and an exit status.

Exit status: 0 success, 2 bad input, 3 could not solve (degenerate data, no convergence), 1 internal error.
"""
from __future__ import annotations

import logging
import sys
import traceback
import warnings

from mirror_fg.cli.bench import cmd_live, cmd_pattern
from mirror_fg.cli.commands import cmd_calibrate, cmd_calibrate_many, cmd_detect, cmd_plan, cmd_report, cmd_simulate
from mirror_fg.cli.export_cmd import cmd_export
from mirror_fg.cli.history_cmd import cmd_history
from mirror_fg.cli.parser import build_parser
from mirror_fg.cli.printing import EXIT_INTERNAL, _error_line, _one_line, _Printer
from mirror_fg.cli.verify_cmd import cmd_verify
from mirror_fg.core.errors import MirrorFgError

__all__ = ["main", "build_parser"]

COMMANDS = {"live": cmd_live, "pattern": cmd_pattern, "plan": cmd_plan, "simulate": cmd_simulate,
            "calibrate": cmd_calibrate, "calibrate-many": cmd_calibrate_many, "detect": cmd_detect, "report": cmd_report,
            "verify": cmd_verify,
            "export": cmd_export,
            "history": cmd_history}


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
    notes = _Notes(out)  # the camera a camchain gave: printed without -v too
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
