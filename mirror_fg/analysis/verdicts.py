"""The likelihood-ratio test of ``verify`` (``verify.py``) and of an arm's mounts (``verify_arm.py``): the
verdicts and their document, the detectable move, the stored result's dispersion and points, the fits'
lowest run, the seen directions and the free fit's prior (the module docstring of ``verify.py`` gives the
test; frames and units as there).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import gtsam
import numpy as np
from scipy import optimize as scipy_optimize
from scipy import stats

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.data import Dataset
from mirror_fg.solver.model.optimizer import run_optimizer

__all__ = [
    "MOVED", "NOT_MOVED", "CANNOT_TELL", "UNCHECKED", "POWER", "SEEN", "FREE_WEIGHT", "UNSEEN_WEIGHT", "CameraVerdict",
    "Verification", "detectable_noncentrality", "stored_dispersion", "stored_points", "lowest_fit", "seen_directions",
    "free_information", "TestedFits", "verdict_of", "advice_for",
]

MOVED, NOT_MOVED, CANNOT_TELL = "moved", "not moved", "cannot tell"
#: The advice of a `cannot tell` whose stored bounds could not be checked (dispersion with nu = 0).
UNCHECKED = ("the stored result's images cannot be checked against each other (each was needed to determine it), "
             "so its bounds may be too narrow: calibrate again with more placements")
#: The power at which the detectable move is stated.
POWER = 0.9
#: A direction of the pose whose new-data information is below this fraction of the stored information
#: is not seen by the new data (numerically zero where a placement absorbs it: ~1e-10 measured).
SEEN = 1e-6
#: The "free" fit's prior in the seen directions, as a fraction of the stored information: it keeps LM's
#: system regular and changes ``d2`` by less than this over ``SEEN`` (1 %).
FREE_WEIGHT = 1e-8
#: The "free" fit's prior in the unseen directions, as a fraction of the stored information: it picks one
#: pose of the family the images cannot tell apart (the one nearest the stored), lets a direction with
#: information below ``SEEN`` change ``d2`` by less than ``SEEN`` over this (1 % of a chi-square degree of
#: freedom) and, unlike the whole stored prior, lets the free camera follow that family after a large move.
UNSEEN_WEIGHT = 1e-4
@dataclass(frozen=True)
class CameraVerdict:
    """One camera's answer. ``move``: ``[dtheta (rad), dt (m)]`` new minus stored and ``covariance`` its
    combined 6 x 6 (``S + N^-1``), both None where the new data do not determine the pose (``dof < 6``);
    ``detectable_rad`` / ``detectable_m``: the smallest rotation / translation detectable at ``alpha``
    with power :data:`POWER` in the worst direction (inf where ``dof < 6``); ``advice``: what to add."""

    name: str
    verdict: str
    p_value: float
    mahalanobis2: float
    dof: int
    move: np.ndarray | None
    covariance: np.ndarray | None
    detectable_rad: float
    detectable_m: float
    advice: str
    #: The result's dispersion ``s2`` (the test divides by ``max(1, s2)``; NaN where ``nu = 0``, 1.0 where
    #: the result stores none) and its degrees of freedom ``nu`` (None where it stores none: chi-square).
    dispersion: float = 1.0
    dispersion_dof: float | None = None

    @property
    def exit_code(self) -> int:
        return {MOVED: 4, NOT_MOVED: 0, CANNOT_TELL: 5}[self.verdict]

    def to_dict(self) -> dict[str, Any]:
        """This camera's entry of verification@1 (docs/formats.md)."""
        move = sigma3 = None
        if self.move is not None and self.covariance is not None:
            move = {"rotation_deg": np.rad2deg(self.move[:3]).tolist(), "position_mm": (1e3 * self.move[3:]).tolist()}
            sd3 = 3.0 * np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
            sigma3 = {"rotation_deg": np.rad2deg(sd3[:3]).tolist(), "position_mm": (1e3 * sd3[3:]).tolist()}
        return {"verdict": self.verdict, "p_value": self.p_value, "mahalanobis2": self.mahalanobis2, "dof": self.dof,
                "move": move, "sigma3": sigma3,
                "detectable": {"rotation_deg": _finite(math.degrees(self.detectable_rad)),
                               "position_mm": _finite(1e3 * self.detectable_m)},
                "advice": self.advice or None,
                "dispersion": None if self.dispersion_dof is None else {"factor": self.dispersion,
                                                                        "dof": self.dispersion_dof}}


@dataclass(frozen=True)
class Verification:
    """Every camera's verdict; ``fused``: ``{camera: (R, t, covariance)}``, the stored estimate combined
    with the new data (the stored transforms as priors), for ``--update``."""

    cameras: dict[str, CameraVerdict]
    alpha: float
    tolerance_mm: float
    tolerance_deg: float
    fused: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]

    @property
    def verdict(self) -> str:
        """``moved`` if any camera moved, else ``cannot tell`` if any cannot tell, else ``not moved``."""
        verdicts = {v.verdict for v in self.cameras.values()}
        return MOVED if MOVED in verdicts else CANNOT_TELL if CANNOT_TELL in verdicts else NOT_MOVED

    @property
    def exit_code(self) -> int:
        return {MOVED: 4, NOT_MOVED: 0, CANNOT_TELL: 5}[self.verdict]

    def to_dict(self, result_path: str, data_path: str) -> dict[str, Any]:
        """The verification@1 document (docs/formats.md)."""
        return {"format": "mirror-fg/verification@1", "result": result_path, "data": data_path, "alpha": self.alpha,
                "tolerance": {"rotation_deg": self.tolerance_deg, "position_mm": self.tolerance_mm},
                "verdict": self.verdict, "cameras": {n: v.to_dict() for n, v in self.cameras.items()}}


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def detectable_noncentrality(dof: int, alpha: float, power: float = POWER, denominator_dof: float | None = None
                              ) -> float:
    """The non-centrality ``lambda*`` at which a chi-square test of ``dof`` degrees of freedom at level
    ``alpha`` rejects with probability ``power`` (non-central chi-square); with ``denominator_dof`` ``nu``,
    an F-test of ``(dof, nu)`` degrees of freedom (non-central F)."""
    if denominator_dof is None:
        critical = stats.chi2.isf(alpha, dof)

        def shortfall(ncp: float) -> float:
            return float(stats.ncx2.sf(critical, dof, ncp)) - power
    else:
        critical = stats.f.isf(alpha, dof, denominator_dof)

        def shortfall(ncp: float) -> float:
            return float(stats.ncf.sf(critical, dof, denominator_dof, ncp)) - power

    high = 1.0
    while shortfall(high) < 0:
        high *= 2.0
    return float(scipy_optimize.brentq(shortfall, 1e-9, high, xtol=1e-9))


# --------------------------------------------------------------------------------------------------
# The stored result


def stored_dispersion(result: Mapping[str, Any]) -> tuple[float, float] | None:
    """``(s2, nu)`` of the result's ``dispersion`` (``s2`` NaN where ``nu`` is 0), None without one."""
    block = result.get("dispersion")
    if not block:
        return None
    dof = float(block["dof"])
    factor = block.get("factor")
    return (float(factor) if factor is not None and dof > 0.5 else math.nan), dof


def stored_points(result: Mapping[str, Any], dataset: Dataset, source: str) -> dict[str, np.ndarray]:
    """The result's reconstruction points, once the new data are checked to be of its set-up: a known target,
    the residuals' units (pixels or normalized) as the data's, every unknown point of the data in the result."""
    if not dataset.fiducials:
        raise DatasetError(f"{dataset.source}: no fiducials: verify needs the known target the result was made with")
    units = (result.get("residuals") or {}).get("units")
    if units is not None and (units == "px") != (dataset.camera is not None or dataset.cameras is not None):
        raise DatasetError(f"{source}: its residuals are in {units} but the data are "
                           f"{'pixels' if units != 'px' else 'normalized'}: the result and the data are from "
                           "different set-ups")
    points = {n: np.array(e["xyz"], dtype=float) for n, e in (result.get("points") or {}).items()}
    missing = [n for n in dataset.reconstruction_point_names if n not in points]
    if missing:
        raise DatasetError(f"{dataset.source}: point {missing[0]!r} is neither a fiducial nor a point of the result "
                           f"{source}: verify takes the points from the result")
    return points


def lowest_fit(data: gtsam.NonlinearFactorGraph, priors: list, starts: list[gtsam.Values],
               params: gtsam.LevenbergMarquardtParams, source: str, unconstrained) -> tuple[gtsam.Values, float]:
    """LM on ``data`` and ``priors`` from each of ``starts``: the lowest ``(values, cost)``;
    ``unconstrained(error)`` words an unknown the graph leaves free."""
    graph = gtsam.NonlinearFactorGraph(data)
    for factor in priors:
        graph.add(factor)
    best: tuple[gtsam.Values, float] | None = None
    for start in starts:
        _, values, _ = run_optimizer(graph, start, params, source, unconstrained)
        cost = float(graph.error(values))
        if best is None or cost < best[1]:
            best = (values, cost)
    assert best is not None
    return best


def seen_directions(stored_tangent: np.ndarray, information: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lambda, U, L)``: the new data's information relative to the stored (module docstring)."""
    L = np.linalg.cholesky(stored_tangent)
    lam, U = np.linalg.eigh(L.T @ information @ L)
    return lam, U, L


def free_information(lam: np.ndarray, U: np.ndarray, L: np.ndarray) -> np.ndarray:
    """The free fit's prior (tangent information): :data:`FREE_WEIGHT` of the stored one in the seen
    directions, :data:`UNSEEN_WEIGHT` of it in the unseen ones (module docstring)."""
    weights = np.where(lam > SEEN, FREE_WEIGHT, UNSEEN_WEIGHT)
    L_inv = np.linalg.inv(L)
    F = L_inv.T @ (U * weights) @ U.T @ L_inv
    return 0.5 * (F + F.T)


# --------------------------------------------------------------------------------------------------
# The verdict


class TestedFits(Protocol):
    """What a verdict reads of the fits (``verify._Fits``, the arm's ``verify_arm._ArmFits``)."""

    stored: Any
    noun: str

    def pose_key(self, name: str) -> int: ...

    def pose_information(self, name: str, values: gtsam.Values) -> np.ndarray: ...


def verdict_of(name: str, d2: float, dof: int, p: float, free: gtsam.Values, fits: TestedFits, ncp: float, alpha: float,
             tolerance_mm: float, tolerance_deg: float, scale: float = 1.0) -> CameraVerdict:
    R_s, t_s, S = fits.stored[name]
    ncp = ncp * scale  # the detectable d2 in the stored units: the test divides d2 by scale
    move = combined = None
    detectable_rad = detectable_m = math.inf
    if dof == 6:
        estimate = free.atPose3(fits.pose_key(name))
        R, t = estimate.rotation().matrix(), np.asarray(estimate.translation(), float)
        # the move in the uncertainty convention: R_new = Exp(dtheta) R_stored, t_new = t_stored + dt
        move = np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R @ R_s.T)), t - t_s])
        new = covariance_from_pose3(R, np.linalg.inv(fits.pose_information(name, free)))
        combined = S + 0.5 * (new + new.T)
        detectable_rad = math.sqrt(ncp * float(np.linalg.eigvalsh(combined[:3, :3])[-1]))
        detectable_m = math.sqrt(ncp * float(np.linalg.eigvalsh(combined[3:, 3:])[-1]))
        combined = scale * combined  # the bounds the images' agreement supports
    if p < alpha:
        verdict, advice = MOVED, ""
    elif math.degrees(detectable_rad) <= tolerance_deg and 1e3 * detectable_m <= tolerance_mm:
        verdict, advice = NOT_MOVED, ""
    else:
        verdict, advice = CANNOT_TELL, advice_for(dof, S, ncp, tolerance_mm, tolerance_deg, fits.noun)
    return CameraVerdict(name, verdict, p, d2, dof, move, combined, detectable_rad, detectable_m, advice)


def advice_for(dof: int, stored: np.ndarray, ncp: float, tolerance_mm: float, tolerance_deg: float,
            noun: str = "camera") -> str:
    """What to add for a ``cannot tell`` (``noun``: what is tested, a camera or an arm's mount)."""
    if dof < 6:
        return (f"the new images see {dof} of the {noun}'s 6 degrees of freedom (a mirror placement hides any "
                "rotation about a line in its plane): add images at other mirror placements (mirror-fg plan --next), "
                "or at a mirror the result knows still standing where it stood (its label kept, --standing-mirror)")
    rotation = math.degrees(math.sqrt(ncp * float(np.linalg.eigvalsh(stored[:3, :3])[-1])))
    position = 1e3 * math.sqrt(ncp * float(np.linalg.eigvalsh(stored[3:, 3:])[-1]))
    if rotation > tolerance_deg or position > tolerance_mm:
        return (f"the stored result alone is too uncertain for this tolerance (no move below {rotation:.2g} deg / "
                f"{position:.2g} mm could be told apart from it): calibrate again with more placements")
    return "the new images are too few for the tolerance: add images at other mirror placements (mirror-fg plan --next)"
