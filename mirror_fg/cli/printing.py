"""What the command prints: the human output on stdout (a failing stdout never changes the exit status
or the files), one-line errors and warnings on stderr, and their quoting of user data."""
from __future__ import annotations

import os
import re
import sys

EXIT_OK, EXIT_INTERNAL = 0, 1  # bad input and unsolvable data: MirrorFgError.exit_code (2, 3)


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


#: Longest run of user data (a path, a value) quoted in an error line.
_MAX_QUOTE = 80


def _one_line(message: str) -> str:
    """``message`` on one line, any run of more than _MAX_QUOTE non-blank characters elided in the middle."""
    def elide(match: re.Match[str]) -> str:
        word = match.group(0)
        half = (_MAX_QUOTE - 3) // 2
        return word[:half] + "..." + word[-half:]

    return re.sub(r"\S{%d,}" % (_MAX_QUOTE + 1), elide, " ".join(str(message).split()))


def _error_line(text: str) -> None:
    try:
        print(text, file=sys.stderr, flush=True)
    except OSError:
        pass
