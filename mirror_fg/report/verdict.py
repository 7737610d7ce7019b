"""The one verdict on a ``mirror-fg/result@1``: computed once, stored in the result, printed by the console
and shown as the report's headline (so the two can never disagree).

:func:`judge` looks at what the result holds and, given its dataset, at the residuals' pattern, and returns a
frozen :class:`Verdict`: its level (``good``, ``check``, or ``unknown`` when there is nothing to judge by),
the problems found (each a short title for the report's headline and a sentence saying what to do) and the
facts checked. :func:`with_verdict` stores it under the result's ``verdict`` key (docs/formats.md, Result
file); :meth:`Verdict.from_dict` reads it back. The checks:

- convergence, and a final cost far above its expected value (``solver.model.lm.plausible``);
- the noise model: the residuals' size over what ``pixel_sigma`` predicts, ``sqrt(chi2 / dof)`` (docs/formats.md's
  RMS whitened residual), against the two-sided :data:`NOISE_CONFIDENCE` interval of ``sqrt(chi2_dof / dof)``
  with the solve's own degrees of freedom (:func:`noise_band`), never narrower than :data:`NOISE_BAND`;
- weak geometry (:func:`weak_geometry`): 3-sigma bounds wider than a linearised covariance can describe
  (a rotation beyond :data:`LINEAR_LIMIT_DEG`, a position bound comparable with the scene's size,
  :data:`POSITION_LIMIT`), or too few spare measurements (:data:`MIN_MEAN_REDUNDANCY`);
- parts of the capture that disagree (result@1 ``inconsistency``);
- with the dataset: images far worse than the others, residuals that grow towards the image edge.

Units: degrees, millimetres, metres; residuals in pixels, or normalized units for a dataset without a camera.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.fit import plausible

if TYPE_CHECKING:
    from mirror_fg.data import Dataset
    from mirror_fg.report.residuals import Residuals

__all__ = ["Verdict", "Finding", "judge", "with_verdict", "stored_verdict", "noise_band", "noise_note",
           "noise_fit", "weak_geometry", "scene_size", "cost_warning", "NOISE_BAND", "NOISE_CONFIDENCE", "LINEAR_LIMIT_DEG",
           "MIN_MEAN_REDUNDANCY", "POSITION_LIMIT", "WEAK_GEOMETRY", "GOOD", "CHECK", "UNKNOWN", "unknown_count",
           "without_target"]

GOOD, CHECK, UNKNOWN = "good", "check", "unknown"

#: The noise-model check's confidence: a correct ``pixel_sigma`` puts the residuals inside the band at least
#: this often (two-sided chi-square interval of the cost with the solve's degrees of freedom).
NOISE_CONFIDENCE = 0.99
#: The band is never narrower than this factor range: a ``pixel_sigma`` off by less than a factor 2 changes
#: the 3-sigma bounds by less than that, which many spare measurements would otherwise flag.
NOISE_BAND = (0.5, 2.0)
#: A linearised covariance describes a rotation error while it stays small: at 10 deg the neglected
#: second-order term (θ² / 2 of θ) is 9 % of it, and it grows quadratically beyond.
LINEAR_LIMIT_DEG = 10.0
#: A position bound (camera, mirror placement, point) above this share of the scene's size (the largest of
#: the camera-base distance and the mirrors' and points' distances from the camera) is comparable with the
#: scene itself.
POSITION_LIMIT = 0.5
#: The mean redundancy number, spare measurements over measurements ((2N - p) / 2N): below 0.2 most of
#: what is measured goes into fixing the unknowns, and a wrong measurement can neither be seen nor told apart
#: (Förstner's reliability classes put redundancy numbers below 0.1 as uncontrolled, 0.1-0.3 as poorly
#: controlled).
MIN_MEAN_REDUNDANCY = 0.2
#: The plain words that open the weak-geometry problem (console, result, report).
WEAK_GEOMETRY = "weak geometry: the data barely determine the answer; add placements (plan --next)"


@dataclass(frozen=True)
class Finding:
    """One problem: ``check`` (a stable key: ``converged``, ``cost``, ``noise``, ``bounds``, ``weak_geometry``,
    ``inconsistency``, ``images``, ``distortion``), ``title`` (a few words for the report's headline) and
    ``text`` (what it is and what to do)."""

    check: str
    title: str
    text: str


@dataclass(frozen=True)
class Verdict:
    """Does the result look right. ``level``: :data:`GOOD`, :data:`CHECK` or :data:`UNKNOWN` (nothing to judge
    by); ``problems``: what is wrong (empty unless ``check``); ``facts``: what was checked and found right;
    ``fit``: the sentence on the residuals against the noise model ('' without a cost)."""

    level: str
    problems: tuple[Finding, ...] = ()
    facts: tuple[str, ...] = ()
    fit: str = ""

    @property
    def good(self) -> bool:
        return self.level == GOOD

    @property
    def headline(self) -> str:
        """The report's headline."""
        if self.problems:
            return "Check before use: " + "; ".join(p.title for p in self.problems)
        if self.level == GOOD:
            return "Looks right: converged, and the residuals are what the noise model predicts"
        return "No optimizer or residual information in the result"

    @property
    def reasons(self) -> list[str]:
        """The report's bullets: each problem's sentence, then the facts."""
        return [p.text for p in self.problems] + list(self.facts)

    @property
    def line(self) -> str:
        """The console's one ``verdict:`` line."""
        if self.problems:
            fit = "" if any(p.check == "noise" for p in self.problems) or not self.fit else f"; {self.fit}"
            return "verdict: CHECK: " + "; ".join(p.text for p in self.problems) + fit
        if self.level == GOOD:
            return f"verdict: looks right: {self.fit}"
        return "verdict: no cost to judge the noise model by (the report has the residuals)"

    def to_dict(self) -> dict[str, Any]:
        """result@1's ``verdict`` block (docs/formats.md)."""
        return {"level": self.level, "headline": self.headline, "console": self.line,
                "problems": [{"check": p.check, "title": p.title, "text": p.text} for p in self.problems],
                "facts": list(self.facts), "fit": self.fit}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Verdict:
        """The verdict stored in a result (its ``verdict`` block); ValueError when it is malformed."""
        level = data.get("level")
        if level not in (GOOD, CHECK, UNKNOWN):
            raise ValueError(f"verdict.level must be one of {GOOD}, {CHECK}, {UNKNOWN}, got {level!r}")
        problems = tuple(Finding(str(p["check"]), str(p["title"]), str(p["text"])) for p in data.get("problems") or [])
        if (level == CHECK) != bool(problems):
            raise ValueError("verdict: level 'check' goes with problems, and only it")
        return cls(level, problems, tuple(str(f) for f in data.get("facts") or []), str(data.get("fit") or ""))


def stored_verdict(result: Mapping[str, Any]) -> Verdict | None:
    """The verdict the result carries (``calibrate`` stores it), or None for a result without one or with a
    malformed one (then it is judged again)."""
    data = result.get("verdict")
    if not isinstance(data, Mapping):
        return None
    try:
        return Verdict.from_dict(data)
    except (ValueError, KeyError, TypeError):
        return None


def with_verdict(result: Mapping[str, Any], dataset: Dataset | None = None, *,
                 pixel_sigma: float | None = None) -> dict[str, Any]:
    """``result`` with its :func:`judge` verdict stored under ``verdict`` (a new dictionary)."""
    return {**result, "verdict": judge(result, dataset, pixel_sigma=pixel_sigma).to_dict()}


# --------------------------------------------------------------------------------------------------
# The noise model
# --------------------------------------------------------------------------------------------------


def noise_band(dof: float, confidence: float = NOISE_CONFIDENCE) -> tuple[float, float]:
    """The range of ``sqrt(chi2 / dof)`` (the residuals over their predicted size) that a correct
    ``pixel_sigma`` stays within with probability ``confidence``: the two-sided chi-square interval with
    ``dof`` spare measurements, widened to :data:`NOISE_BAND` where it is narrower."""
    if not (dof > 0 and math.isfinite(dof)):
        return NOISE_BAND
    tail = (1.0 - confidence) / 2.0
    # The chi-square's quantiles are bounded (Laurent & Massart 2000, Lemma 1: P(X - k >= 2 sqrt(k x) + 2 x)
    # and P(k - X >= 2 sqrt(k x)) are at most exp(-x)): where the bounds already lie inside NOISE_BAND, so
    # does the interval, and the band is NOISE_BAND without SciPy (0.3 s to import: a small capture's command)
    x = math.log(1.0 / tail)
    if (dof - 2.0 * math.sqrt(dof * x) >= NOISE_BAND[0] ** 2 * dof
            and dof + 2.0 * math.sqrt(dof * x) + 2.0 * x <= NOISE_BAND[1] ** 2 * dof):
        return NOISE_BAND
    from scipy.special import chdtri  # type: ignore[import-untyped]  # the upper-tail chi-square quantile (lighter than scipy.stats)

    low = math.sqrt(float(chdtri(dof, 1.0 - tail)) / dof)
    high = math.sqrt(float(chdtri(dof, tail)) / dof)
    return min(low, NOISE_BAND[0]), max(high, NOISE_BAND[1])


def _band_words(band: tuple[float, float], dof: float, coordinates: float | None = None) -> str:
    of = f" of {coordinates:.0f} measured coordinates" if coordinates is not None else " measured coordinates"
    return (f"a correct pixel_sigma gives {band[0]:.2f}-{band[1]:.2f} × with {dof:.0f} spare{of}, "
            f"{100 * NOISE_CONFIDENCE:.0f} % of the time")


def noise_note(ratio: float, sigma: float, units: str, dof: float = float("nan"),
               coordinates: float | None = None) -> str:
    """'' when ``ratio`` (the residuals' size over what ``sigma`` predicts) is inside :func:`noise_band`
    of ``dof``; else what it means for ``pixel_sigma`` and the bounds, with the band and its confidence
    (``coordinates``: the measured coordinates 2N, for the words)."""
    band = noise_band(dof)
    fits = f"the residuals fit σ ≈ {sigma * ratio:.2g} {units}"
    if ratio < band[0]:
        return (f"pixel_sigma {sigma:.3g} {units} is too large: {fits}, so the 3-sigma bounds are about "
                f"{1 / ratio:.1f} × too wide (set pixel_sigma to your detector's accuracy; {_band_words(band, dof, coordinates)})")
    if ratio > band[1]:
        return (f"the residuals are {ratio:.1f} × what pixel_sigma {sigma:.3g} {units} predicts ({fits}): outliers, "
                f"a wrong camera model or too small a pixel_sigma; the 3-sigma bounds are too narrow "
                f"({_band_words(band, dof, coordinates)})")
    return ""


def without_target(result: Mapping[str, Any]) -> bool:
    """Whether the result is of data without a known target (``fiducials: {}``): the first camera's pose
    is then exactly the identity with an exactly zero covariance (not estimated)."""
    cov = result.get("covariance_cam_base")
    T = result["T_cam_base"]
    return (cov is not None and not np.any(np.asarray(cov, dtype=float))
            and np.array_equal(np.asarray(T["R"], dtype=float), np.eye(3)) and not np.any(np.asarray(T["t"], dtype=float)))


def unknown_count(result: Mapping[str, Any]) -> int:
    """The solve's unknowns p: the pose (6; 6 per camera with ``cameras``), each mirror placement and
    reconstruction point (3 each), each estimated intrinsic (of every camera with ``cameras``): the degrees
    of freedom the residuals lose at the optimum."""
    from mirror_fg.io.result import mirror_vectors, points

    cameras = result.get("cameras") or {}
    blocks = [entry.get("camera") or {} for entry in cameras.values()] if cameras else [result.get("camera") or {}]
    poses = 6 * max(len(cameras), 1) - (7 if without_target(result) else 0)  # the first pose fixed, and the scale
    return (poses + 3 * len(mirror_vectors(result)) + 3 * len(points(result))
            + sum(len(block.get("estimated") or []) for block in blocks))


def noise_fit(result: Mapping[str, Any], pixel_sigma: float | None = None) -> tuple[float, float, float] | None:
    """(residuals over their predicted size, the pixel_sigma used, the spare measurements dof), or None.

    With N measurements and p unknowns the expected cost is dof / 2 = (2N - p) / 2, so N = expected + p / 2
    and the predicted RMS is sigma sqrt(2 expected / N) (sqrt(2) sigma less one degree of freedom per
    unknown). Without ``pixel_sigma`` it is read from the plain final cost, final = N RMS^2 / (2 sigma^2),
    i.e. ratio = sqrt(final / expected): not after a robust kernel, whose cost is smaller.
    """
    opt, res = result.get("optimizer") or {}, result.get("residuals") or {}
    final, expected, rms = opt.get("final_error"), opt.get("expected_final_error"), res.get("rms_px")
    if not all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in (expected, rms)):
        return None
    expected, rms = float(expected), float(rms)  # type: ignore[arg-type]  # checked above (all() does not narrow)
    dof = 2.0 * expected
    measurements = expected + unknown_count(result) / 2
    if pixel_sigma is not None and pixel_sigma > 0:
        return rms / (pixel_sigma * math.sqrt(2 * expected / measurements)), float(pixel_sigma), dof
    if not (isinstance(final, (int, float)) and math.isfinite(final) and final > 0):
        return None
    final = float(final)
    return math.sqrt(final / expected), rms * math.sqrt(measurements / (2 * final)), dof


def cost_warning(opt: Mapping[str, Any]) -> str | None:
    """Why the optimizer's final cost is implausible (far above its expected value at the optimum), or None."""
    final, expected = opt.get("final_error"), opt.get("expected_final_error")
    if final is None or expected is None or not (math.isfinite(final) and math.isfinite(expected)):
        return None
    if plausible(final, expected):
        return None
    return (f"final cost {final:.4g} is far above its expected {expected:.4g} at the optimum: a local minimum, "
            "outliers (try --robust) or a pixel_sigma that is too small")


# --------------------------------------------------------------------------------------------------
# Weak geometry
# --------------------------------------------------------------------------------------------------


def _largest(values: Any) -> float:
    arr = np.asarray(values if values is not None else [], dtype=float)
    arr = arr[np.isfinite(arr)]
    return float(arr.max()) if arr.size else 0.0


def _pose_bounds(result: Mapping[str, Any]) -> list[tuple[str, float, float]]:
    """``(what, rotation 3-sigma deg, position 3-sigma mm)`` of every estimated camera pose (its
    ``T_base_cam`` bounds: the camera's pose on the robot)."""
    from mirror_fg.io.result import base_cam_sigma3

    cameras = result.get("cameras") or {}
    entries = [(f"camera {name}", entry.get("sigma3_base_cam")) for name, entry in cameras.items()] if cameras \
        else [("T_base_cam", base_cam_sigma3(result))]
    return [(what, _largest(sigma.get("rotation_deg")), _largest(sigma.get("position_mm")))
            for what, sigma in entries if sigma]


def scene_size(result: Mapping[str, Any]) -> float:
    """The scene's size, metres: the largest of every camera's distance from the base origin, every mirror
    placement's distance from its camera and every reconstruction point's from the first camera."""
    from mirror_fg.io.result import pose

    cameras = result.get("cameras") or {}
    poses = [entry["T_cam_base"] for entry in cameras.values()] if cameras else [result["T_cam_base"]]
    distances = [float(np.linalg.norm(pose(T)[1])) for T in poses]
    distances += [float(np.linalg.norm(entry["v"])) for entry in result.get("mirrors") or []]
    R, t = pose(poses[0])  # reconstruction points are in the base frame: their distance from the first camera
    distances += [float(np.linalg.norm(R @ np.asarray(entry["xyz"], dtype=float) + t))
                  for entry in (result.get("points") or {}).values()]
    return max(distances, default=0.0)


def weak_geometry(result: Mapping[str, Any]) -> str | None:
    """Why the data barely determine the answer, or None: a pose's 3-sigma rotation beyond
    :data:`LINEAR_LIMIT_DEG` (where a linearised covariance no longer describes the error), a camera, mirror
    or point position bound above :data:`POSITION_LIMIT` of :func:`scene_size`, or a mean redundancy number
    below :data:`MIN_MEAN_REDUNDANCY`."""
    reasons = []
    size_mm = 1000.0 * scene_size(result)
    limit_mm = POSITION_LIMIT * size_mm
    for what, rotation, position_mm in _pose_bounds(result):
        if rotation > LINEAR_LIMIT_DEG:
            reasons.append(f"{what}'s 3-sigma rotation ±{rotation:.1f} deg (beyond about {LINEAR_LIMIT_DEG:g} deg a "
                           "linearised covariance no longer describes the error)")
        if size_mm > 0 and position_mm > limit_mm:
            reasons.append(f"{what}'s 3-sigma position ±{position_mm:.0f} mm in a scene of {size_mm:.0f} mm")
    loose = [f"mirror {e['mirror']} placement {e['config']} ±{_largest(e['sigma3_mm']):.0f} mm"
             for e in result.get("mirrors") or [] if e.get("sigma3_mm") and _largest(e["sigma3_mm"]) > limit_mm > 0]
    loose += [f"point {name} ±{_largest(e['sigma3_mm']):.0f} mm"
              for name, e in (result.get("points") or {}).items() if e.get("sigma3_mm") and _largest(e["sigma3_mm"]) > limit_mm > 0]
    if loose:
        reasons.append(", ".join(loose[:3]) + (f" and {len(loose) - 3} more" if len(loose) > 3 else "")
                       + f" (3-sigma) in a scene of {size_mm:.0f} mm")
    expected = (result.get("optimizer") or {}).get("expected_final_error")
    spare = 2.0 * float(expected) if isinstance(expected, (int, float)) and math.isfinite(expected) else None
    if spare is not None:
        measurements = spare + unknown_count(result)
        if measurements > 0 and spare / measurements < MIN_MEAN_REDUNDANCY:
            reasons.append(f"only {spare:.0f} spare of {measurements:.0f} measured coordinates (a wrong one can be "
                           "neither seen nor told apart)")
    return f"{WEAK_GEOMETRY}: " + "; ".join(reasons) if reasons else None


# --------------------------------------------------------------------------------------------------
# The verdict
# --------------------------------------------------------------------------------------------------


def judge(result: Mapping[str, Any], dataset: Dataset | None = None, *, residuals: Residuals | None = None,
          pixel_sigma: float | None = None) -> Verdict:
    """The verdict on a validated result@1 dictionary (module docstring).

    ``dataset``: the dataset it was computed from, for the residuals' pattern (computed here unless
    ``residuals`` gives them) and its ``pixel_sigma`` (unless ``pixel_sigma`` is given; a dataset with
    per-point sigmas is judged by the sigma its cost implies). Without either, the noise model is judged by
    the sigma the result's costs imply.
    """
    opt = result.get("optimizer") or {}
    units = "px" if (result.get("residuals") or {}).get("units", "px") == "px" else "(normalized)"
    problems: list[Finding] = []
    facts: list[str] = []
    if opt.get("converged") is False:
        problems.append(Finding("converged", "not converged", "the optimizer did not converge"))
    elif opt.get("converged"):
        facts.append("optimizer converged")
    if pixel_sigma is None and dataset is not None and not getattr(dataset, "point_sigma", None):
        pixel_sigma = dataset.pixel_sigma
    fit = noise_fit(result, pixel_sigma)
    fit_words = ""
    if fit is not None:
        ratio, sigma, dof = fit
        coordinates = dof + unknown_count(result)
        fit_words = (f"residuals {ratio:.2f} × their predicted size under pixel_sigma {sigma:.3g} {units} "
                     f"({_band_words(noise_band(dof), dof, coordinates)}; {unknown_count(result)} unknowns)")
        note = noise_note(ratio, sigma, units, dof, coordinates)
        if note:
            problems.append(Finding("noise", "pixel_sigma does not fit the residuals", note))
        else:
            facts.insert(0, fit_words)
    warning = cost_warning(opt)
    if warning and not any(p.check == "noise" for p in problems):
        problems.append(Finding("cost", "final cost implausible", warning))
    if not _finite_bounds(result):
        problems.append(Finding("bounds", "the bounds are not numbers",
                                "some 3-sigma bounds are not finite (nan or inf): the solve did not determine the answer; "
                                "check the lengths' units (metres) and the scale"))
    weak = weak_geometry(result)
    if weak:
        problems.append(Finding("weak_geometry", "weak geometry (the data barely determine the answer)", weak))
    if result.get("inconsistency") is not None:
        problems.append(Finding("inconsistency", "parts of the capture disagree", result["inconsistency"]["message"]))
    excluded = result.get("excluded") or []
    if excluded:
        facts.append(f"{len(excluded)} image(s) or measurement(s) left out of the solve (listed in the result)")
    if dataset is not None and residuals is None:
        residuals = _residuals(result, dataset)
    if residuals is not None and dataset is not None:
        _pattern(result, dataset, residuals, units, problems, facts)
    if problems:
        return Verdict(CHECK, tuple(problems), tuple(facts), fit_words)
    return Verdict(GOOD if fit is not None else UNKNOWN, (), tuple(facts), fit_words)


def _finite_bounds(result: Mapping[str, Any]) -> bool:
    """Whether every 3-sigma bound the result holds (poses, mirrors, points) is a finite number."""
    values: list[Any] = []
    for key in ("sigma3_cam_base", "sigma3_base_cam"):
        values += [v for part in (result.get(key) or {}).values() for v in (part or [])]
    for entry in (result.get("cameras") or {}).values():
        values += [v for part in (entry.get("sigma3_base_cam") or {}).values() for v in (part or [])]
    values += [v for e in result.get("mirrors") or [] for v in (e.get("sigma3_mm") or [])]
    values += [v for e in (result.get("points") or {}).values() for v in (e.get("sigma3_mm") or [])]
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def _residuals(result: Mapping[str, Any], dataset: Dataset) -> Residuals | None:
    """Every measurement's residual, as the report computes them (the general view model's for any
    reflection order, several cameras or no target)."""
    from mirror_fg.core.errors import DatasetError

    try:
        if getattr(dataset, "robot", None) is not None:  # an arm: predicted through the kinematics
            from mirror_fg.report.robot import robot_residuals

            return robot_residuals(result, dataset, "result")
        if not dataset.is_tree:
            from mirror_fg.report.views import view_residuals

            return view_residuals(result, dataset, "result")[0]
        from mirror_fg.report.residuals import residuals_of_valid_result

        return residuals_of_valid_result(result, dataset, "result")
    except DatasetError:  # the dataset is not this result's: no pattern to judge
        return None


def _pattern(result: Mapping[str, Any], dataset: Dataset, residuals: Residuals, units: str,
             problems: list[Finding], facts: list[str]) -> None:
    """The residuals' pattern: images far worse than the others, growth towards the image edge."""
    from mirror_fg.report.diagnostics import image_centre, radial_verdict
    from mirror_fg.report.residuals import OUTLIER_FACTOR

    if not (math.isfinite(residuals.rms) and np.any(residuals.valid)):
        return
    # An image is a problem when it is far worse than the others *and* worse than the noise model allows
    # (sqrt(2) sigma): three times a median far below the noise is still noise.
    flagged = {k: v for k, v in residuals.flagged_images().items() if v > residuals.expected_rms}
    images = (f"{len(flagged)} image(s) above {OUTLIER_FACTOR:g} × the median image RMS and the noise model's "
              f"√2·σ = {residuals.expected_rms:.3g} {residuals.units}")
    if flagged:
        names = ", ".join(list(flagged)[:5]) + (" ..." if len(flagged) > 5 else "")
        problems.append(Finding("images", f"{len(flagged)} image(s) much worse than the others",
                                f"{images} ({names}): a wrong label, a bad detection or a moved camera"))
    else:
        facts.append(images)
    profile = residuals.radial_profile(image_centre(dataset))
    if profile is not None and profile.significant:
        estimated: Sequence[str] = (result.get("camera") or {}).get("estimated") or ()
        problems.append(Finding("distortion", "residuals grow towards the image edge (distortion)",
                                radial_verdict(profile, residuals.units, estimated)))
    elif profile is not None:
        facts.append(radial_verdict(profile, residuals.units))
