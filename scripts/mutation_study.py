"""Mutation study: do the tests catch the one-line bugs a developer could make?

Each :class:`Mutant` is one realistic slip in one line (a sign, an order, a factor, a threshold): the
file, the exact original text (found exactly once, or at ``occurrence``), its replacement and the tests
aimed at that code. For each mutant the repository is copied once to a temporary folder (the working
tree is never changed), the mutant is applied to the copy, its targeted tests run there with pytest,
and the file is restored; a mutant is **killed** when a test fails (or times out), **survived** when
they all pass. The targeted tests must pass on the unchanged copy first (``--no-baseline`` skips that).

Mutants are grouped by the code they belong to in :data:`MUTANTS`; add a group with :func:`register`
(another module can do so, then call :func:`main`), e.g.::

    from mutation_study import Mutant, register
    register("verify", [Mutant("mirror_fg/tools/verify.py", "limit = 3.0", "limit = 30.0",
                               ("tests/test_verify.py",), "the verify limit ten times looser")])

Usage: ``python scripts/mutation_study.py [--group NAME ...] [--list] [--timeout S]``; exit 0 when at
least ``--goal`` (default 90 %) of the mutants run are killed.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What a copy of the repository leaves out (history, caches, builds).
IGNORED = shutil.ignore_patterns(".git", "__pycache__", ".pytest_cache", ".mypy_cache", "*.egg-info", "build",
                                 "dist", "site", ".hypothesis")


@dataclass(frozen=True)
class Mutant:
    """One one-line bug: in ``file`` (relative to the repository), ``original`` becomes ``replacement``;
    ``tests``: the pytest files or node ids aimed at that code; ``why``: the bug in words."""

    file: str
    original: str
    replacement: str
    tests: tuple[str, ...]
    why: str = ""
    occurrence: int | None = None  # which occurrence when ``original`` is not unique (0 = the first)

    def apply(self, text: str) -> str:
        """``text`` with this mutant applied; ValueError when the original is not found as stated."""
        count = text.count(self.original)
        if count == 0:
            raise ValueError(f"{self.file}: the original text is not there: {self.original!r}")
        if self.occurrence is None and count != 1:
            raise ValueError(f"{self.file}: the original text occurs {count} times (give occurrence): {self.original!r}")
        index = -1
        for _ in range((self.occurrence or 0) + 1):
            index = text.index(self.original, index + 1)
        return text[:index] + self.replacement + text[index + len(self.original):]


MUTANTS: dict[str, list[Mutant]] = {}


def register(group: str, mutants: list[Mutant]) -> None:
    """Add ``mutants`` to ``group`` (made if new)."""
    MUTANTS.setdefault(group, []).extend(mutants)


EXACT = ("tests/test_propagation_exact.py",)
register("propagation", [
    Mutant("mirror_fg/solver/start/propagation.py", "for p in reversed(view.reflections):", "for p in view.reflections:",
           EXACT, "a ray carried back through a view's reflections in the order the light met them"),
    Mutant("mirror_fg/solver/start/propagation.py", "self.known.planes[unknown[0]] = (n, 0.5 * float(n @ H[:3, 3]))",
           "self.known.planes[unknown[0]] = (n, 1.0 * float(n @ H[:3, 3]))", EXACT,
           "rule 3's plane distance doubled"),
    Mutant("mirror_fg/solver/start/propagation.py", "return points - 2.0 * np.outer(points @ n - d, n)",
           "return points - 2.0 * np.outer(points @ n + d, n)", EXACT, "a reflection about the plane's mirror image"),
    Mutant("mirror_fg/solver/start/propagation.py", "H[:3, 3] = 2.0 * d * n", "H[:3, 3] = d * n", EXACT,
           "the 4x4 reflection's offset halved"),
    Mutant("mirror_fg/solver/start/propagation.py", "return R.T @ n_c, d_c - float(n_c @ t)",
           "return R.T @ n_c, d_c + float(n_c @ t)", EXACT, "a camera's plane moved to the base with the wrong sign"),
    Mutant("mirror_fg/solver/start/propagation.py", "b += P @ o", "b += o", EXACT,
           "triangulation without projecting the ray origins"),
    Mutant("mirror_fg/solver/start/propagation.py", "found = _best_pnp(points, z, len(view.reflections))",
           "found = _best_pnp(points, z, 0)", EXACT, "rule 3's PnP ignoring the view's parity"),
])

ANALYTIC = ("tests/test_analytic.py",)
PEELING = ANALYTIC + ("tests/test_peeling_exact.py",)
register("peeling", [
    Mutant("mirror_fg/solver/start/peeling.py",
           "distances = np.bincount(children, weights=along, minlength=num_children) / (2.0 * np.maximum(counts, 1))",
           "distances = np.bincount(children, weights=along, minlength=num_children) / np.maximum(counts, 1)",
           PEELING, "eq. (16)'s mirror distances doubled"),
    Mutant("mirror_fg/solver/start/peeling.py",
           "normals = np.linalg.eigh(np.matmul(np.swapaxes(axes, -1, -2), axes))[1][..., 0]  # eq. (15)",
           "normals = np.linalg.eigh(np.matmul(np.swapaxes(axes, -1, -2), axes))[1][..., 2]  # eq. (15)",
           PEELING, "eq. (15)'s normal as the largest eigenvector, not the smallest"),
    # Survives: the alternation's later steps undo most of it (noise-free nodes stay exact; with 0.01 rad of
    # noise the parent moves by ~1e-3 rad, within its own error), so no test of the result can tell.
    Mutant("mirror_fg/solver/start/peeling.py",
           "new_parent = project_to_orthogonal(rotation_sum - 2.0 * np.swapaxes(normals, 1, 2) @ weighted, parent_det)",
           "new_parent = project_to_orthogonal(rotation_sum + 2.0 * np.swapaxes(normals, 1, 2) @ weighted, parent_det)",
           PEELING, "eq. (17)'s average with the reflection's sign flipped (many children)", occurrence=0),
    Mutant("mirror_fg/solver/start/peeling.py",
           "smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)",
           "smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 4.0 * np.pi / 3.0)",
           PEELING, "the closed-form eigenvalue takes another root"),
])

register("pnp", [
    Mutant("mirror_fg/solver/start/pnp.py", "        observed[:, 1] *= -1.0  # eq. (11)\n    candidates = solver(",
           "        observed[:, 0] *= -1.0  # eq. (11)\n    candidates = solver(", ANALYTIC,
           "eq. (11)'s flip of the image about the wrong axis"),
    Mutant("mirror_fg/solver/start/pnp.py", "    flip = num_mirrors % 2 == 1\n    observed = np.array(",
           "    flip = num_mirrors % 2 == 0\n    observed = np.array(", ANALYTIC,
           "the parity of the number of mirrors inverted"),
])

VIEW_FACTOR = ("tests/test_view_factor.py",)
register("factors", [
    Mutant("factors/views.py", "g = 1.0 + float(u @ t_co) / dd", "g = 1.0 - float(u @ t_co) / dd",
           VIEW_FACTOR + ("tests/test_propagation_exact.py",), "a mirror vector moved to another camera's frame wrongly"),
    Mutant("factors/views.py", "x = x - 2.0 * v[:, None] * s[None, :]  # eq. (3): M x + 2 v",
           "x = x - v[:, None] * s[None, :]  # eq. (3): M x + 2 v", VIEW_FACTOR, "eq. (3) reflecting half-way"),
    Mutant("factors/views.py", "ds -= 2.0 * np.outer(v @ dv, vx) / vv**2", "ds -= np.outer(v @ dv, vx) / vv**2",
           VIEW_FACTOR, "a term of the mirror Jacobian halved"),
    Mutant("factors/views.py", "dx[:, c:c + 3, :] = -np.einsum(\"ij,jkn->ikn\", R_c, _skew_many(B))",
           "dx[:, c:c + 3, :] = np.einsum(\"ij,jkn->ikn\", R_c, _skew_many(B))", VIEW_FACTOR,
           "the rotation Jacobian's sign"),
    Mutant("tests/reference/reflection.py", "return z - measurement", "return measurement - z", ("tests/test_factors.py",),
           "the custom factor's error with the sign of GTSAM's opposite"),
    Mutant("tests/reference/reflection.py", "jacobians[1 + k] = H_mirrors[k]", "jacobians[1 + k] = -H_mirrors[k]",
           ("tests/test_factors.py",), "the mirror Jacobian's sign"),
])

RIG = ("tests/test_rig.py",)
register("rig", [
    Mutant("mirror_fg/solver/model/rig.py", "J[:3, 0:3] = -R  # dtheta = db - R da", "J[:3, 0:3] = R  # dtheta = db - R da",
           RIG, "the rig covariance's rotation term with the wrong sign"),
    Mutant("mirror_fg/solver/model/rig.py", "J[3:, 9:12] = np.eye(3)", "J[3:, 9:12] = -np.eye(3)", RIG,
           "the rig covariance's position term with the wrong sign"),
    Mutant("mirror_fg/solver/model/rig.py", "T = Transform(R_b, t_b) @ Transform(R_a, t_a).inverse()",
           "T = Transform(R_a, t_a) @ Transform(R_b, t_b).inverse()", RIG, "the rig transform the wrong way round"),
    Mutant("mirror_fg/solver/model/rig.py", "index = np.r_[6 * (n - 1): 6 * n + 6]", "index = np.r_[6 * n: 6 * n + 12]",
           RIG, "the wrong cameras' blocks of the joint covariance"),
])

register("consistency", [
    Mutant("mirror_fg/solver/screen/consistency.py", "threshold = chi2.isf(MOVE_SIGNIFICANCE / len(tested), 6)",
           "threshold = chi2.isf(MOVE_SIGNIFICANCE / len(tested), 3)", ("tests/test_moved_camera_threshold.py",),
           "the moved-camera test with 3 degrees of freedom instead of 6"),
    Mutant("mirror_fg/solver/screen/consistency.py", "threshold = chi2.isf(MOVE_SIGNIFICANCE / len(tested), 6)",
           "threshold = chi2.isf(MOVE_SIGNIFICANCE, 6)", ("tests/test_moved_camera_threshold.py",),
           "the moved-camera test without Bonferroni's correction"),
    Mutant("mirror_fg/solver/screen/consistency.py", "if worst is None or distance > worst[0]:",
           "if worst is None or distance < worst[0]:", ("tests/test_moved_camera_threshold.py",),
           "the least, not the largest, disagreement kept"),
])

LIVE_OUTPUTS = ("tests/test_live_outputs.py",)
register("live", [
    Mutant("mirror_fg/live/session.py", "MOTION_PX = 1.5", "MOTION_PX = 15.0", ("tests/test_live_motion.py",),
           "the motion threshold ten times looser"),
    Mutant("mirror_fg/live/session.py", "SAME_PLACEMENT_PX = 6.0", "SAME_PLACEMENT_PX = 0.6", ("tests/test_live_motion.py",),
           "repeats of one placement counted as new"),
    Mutant("mirror_fg/live/server.py", 'last = self.request.headers.get("Last-Event-ID")', "last = None",
           ("tests/test_live_server.py",), "/events ignoring Last-Event-ID"),
    Mutant("mirror_fg/live/server.py", "if (host or \"\").lower() not in hosts:", "if False:",
           ("tests/test_live_server.py",), "the Host check dropped"),
    Mutant("mirror_fg/live/server.py",
           "if origin is not None and origin.lower() not in {f\"http://{h}\" for h in hosts}:",
           "if origin is not None and origin.lower() in {f\"https://{h}\" for h in hosts}:",
           ("tests/test_live_server.py",), "the Origin check inverted"),
    Mutant("mirror_fg/live/save.py", "if source_kind == \"file\":\n        files.append(source)",
           "if source_kind == \"video\":\n        files.append(source)",
           (LIVE_OUTPUTS[0] + "::test_outputs_that_meet_an_input_or_each_other_are_refused_before_anything_is_written",),
           "the --source video not counted as an input"),
    Mutant("mirror_fg/live/save.py", "        self._write_capture(incomplete=True)\n",
           "        self._write_capture(incomplete=False)\n",
           (LIVE_OUTPUTS[0] + "::test_after_a_sigkill_detect_names_the_saved_folder_incomplete",),
           "the saved capture never marked incomplete while the session runs"),
    Mutant("mirror_fg/cli/bench.py",
           "caught = [s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, \"SIGHUP\", None)) if s is not None]",
           "caught = [signal.SIGINT]",
           (LIVE_OUTPUTS[0] + "::test_a_signal_ends_the_session_with_its_frames_saved_and_its_result",),
           "only Ctrl-C ends the session cleanly"),
    Mutant("mirror_fg/tools/live_page.html",
           "const kind = !target ? \"free\" : (value !== null && value <= target ? \"met\" : \"over\");",
           "const kind = value !== null && target && value <= target ? \"met\" : \"over\";",
           ("tests/test_live_page.py",), "a bound with no target drawn red"),
])


# The groups of the newest code (verify, registry, robot, units, verdict, incremental) live in their own module.
sys.path.insert(0, str(Path(__file__).resolve().parent))
from mutation_groups import groups as _newest_groups  # noqa: E402

for _group, _mutants in _newest_groups(Mutant).items():
    register(_group, _mutants)


def run_tests(copy: Path, tests: tuple[str, ...], timeout: float) -> tuple[bool, str]:
    """Run ``tests`` in ``copy``: (whether they all passed, the last line pytest printed)."""
    env = {**os.environ, "PYTHONPATH": str(copy), "PYTHONDONTWRITEBYTECODE": "1"}
    command = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-m", "not slow", *tests]
    try:
        proc = subprocess.run(command, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, f"timed out after {timeout:g} s"
    lines = [line for line in proc.stdout.strip().splitlines() if line.strip()]
    return proc.returncode == 0, lines[-1] if lines else proc.stderr.strip()[-200:]


def missing(mutant: Mutant) -> str | None:
    """Why ``mutant`` cannot be applied to the working tree (its line changed since it was written), or None."""
    try:
        mutant.apply((ROOT / mutant.file).read_text())
    except (OSError, ValueError) as error:
        return str(error)
    return None


def study(groups: list[str], timeout: float, baseline: bool) -> list[tuple[str, Mutant, bool, str]]:
    """Every mutant of ``groups`` applied in turn to one temporary copy of the repository (those whose
    line is not found are reported and left out)."""
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="mirror-fg-mutants-") as folder:
        copy = Path(folder) / "repo"
        shutil.copytree(ROOT, copy, ignore=IGNORED, symlinks=True)
        if baseline:
            tests = tuple(dict.fromkeys(t for g in groups for m in MUTANTS[g] if missing(m) is None for t in m.tests))
            passed, line = run_tests(copy, tests, timeout * 4)
            if not passed:
                raise SystemExit(f"mutation_study: the targeted tests fail without any mutant: {line}")
            print(f"baseline: {len(tests)} test files/ids pass ({line})", flush=True)
        for group in groups:
            for mutant in MUTANTS[group]:
                if (problem := missing(mutant)) is not None:
                    print(f"line not found {group:12s} {mutant.why}: {problem}", flush=True)
                    continue
                path = copy / mutant.file
                original = path.read_text()
                path.write_text(mutant.apply(original))
                began = time.monotonic()
                try:
                    passed, line = run_tests(copy, mutant.tests, timeout)
                finally:
                    path.write_text(original)
                killed = not passed
                outcomes.append((group, mutant, killed, line))
                print(f"{'killed  ' if killed else 'SURVIVED'} {group:12s} {mutant.file}: {mutant.why} "
                      f"({time.monotonic() - began:.0f} s; {line})", flush=True)
    return outcomes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--group", action="append", choices=sorted(MUTANTS), help="only these groups (repeatable)")
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per mutant's tests (a timeout kills it)")
    parser.add_argument("--goal", type=float, default=90.0, help="percentage of mutants to kill (default 90)")
    parser.add_argument("--no-baseline", action="store_true", help="do not run the targeted tests without mutants first")
    args = parser.parse_args(argv)
    groups = args.group or list(MUTANTS)
    for group in groups:  # an original no longer there (a later change to its line) is named, not fatal
        for mutant in MUTANTS[group]:
            if (problem := missing(mutant)) is not None:
                print(f"line not found {group:12s} {mutant.why}: {problem}", file=sys.stderr)
    if args.list:
        for group in groups:
            for mutant in MUTANTS[group]:
                print(f"{group:12s} {mutant.file}: {mutant.why} -> {', '.join(mutant.tests)}")
        return 0
    outcomes = study(groups, args.timeout, not args.no_baseline)
    killed = sum(1 for *_, k, _ in outcomes if k)
    percentage = 100.0 * killed / len(outcomes) if outcomes else 0.0
    for group in groups:
        mine = [k for g, _, k, _ in outcomes if g == group]
        lost = sum(1 for m in MUTANTS[group] if missing(m) is not None)
        print(f"{group:12s} {sum(mine)} of {len(mine)} killed" + (f" ({lost} line(s) not found)" if lost else ""))
    print(f"killed {killed} of {len(outcomes)} mutants ({percentage:.0f} %), survived {len(outcomes) - killed}")
    return 0 if percentage >= args.goal else 1


if __name__ == "__main__":
    sys.exit(main())
