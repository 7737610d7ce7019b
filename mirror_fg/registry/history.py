"""A robot's history: its records printed, written as CSV, and plotted as an HTML page in the report's style.

Frames and units (docs/formats.md): each camera's ``T_base_cam`` (its pose on the robot, base axes); position in
millimetres; rotation in degrees as the rotation vector ``Log(R R_first^T)`` from the camera's first
calibration (the uncertainty convention's ``dtheta``: ``R = Exp(dtheta) R_first``), so that the 3-sigma
``rotation_deg`` of each record is the band around it. A change between consecutive calibrations is flagged
when, along some axis, it exceeds their combined 3-sigma ``sqrt(s1^2 + s2^2)`` (two independent estimates).
"""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mirror_fg.registry.records import HistoryRecord

__all__ = ["Change", "flag_changes", "rotation_from_first_deg", "history_lines", "history_csv", "history_html"]

#: Colours of the verdicts marked on the plots (a verification's, a calibration's).
VERDICT_COLOURS = {"moved": "#c62828", "not moved": "#2e7d32", "cannot tell": "#ef6c00", "check": "#c62828",
                   "looks right": "#2e7d32"}
_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Change:
    """A change of a camera between two consecutive calibrations beyond their combined 3-sigma."""

    camera: str
    before: HistoryRecord
    after: HistoryRecord
    position_mm: tuple[float, float, float]  # after minus before, base axes
    rotation_deg: tuple[float, float, float]  # Log(R_after R_before^T)
    position_sigma3_mm: tuple[float, float, float]  # combined
    rotation_sigma3_deg: tuple[float, float, float]

    def line(self) -> str:
        def axes(values: Sequence[float], bounds: Sequence[float], unit: str) -> str:
            beyond = [f"{a} {v:+.2f} {unit} (3-sigma {b:.2f})" for a, v, b in zip(_AXES, values, bounds) if abs(v) > b]
            return ", ".join(beyond)

        moved = "; ".join(x for x in (axes(self.position_mm, self.position_sigma3_mm, "mm"),
                                      axes(self.rotation_deg, self.rotation_sigma3_deg, "deg")) if x)
        return (f"CHANGED: {self.camera} between run {self.before.run_id} ({_time(self.before)}) and run "
                f"{self.after.run_id} ({_time(self.after)}): {moved}")


def _quaternion_log_deg(q: np.ndarray) -> np.ndarray:
    """The rotation vector (degrees) of a unit quaternion [x, y, z, w]."""
    v, w = q[:3], q[3]
    if w < 0:  # the same rotation, the short way round
        v, w = -v, -w
    norm = float(np.linalg.norm(v))
    if norm < 1e-15:
        return np.degrees(2.0 * v)
    return np.degrees(2.0 * math.atan2(norm, w) / norm * v)


def _quaternion_delta(q_after: Sequence[float], q_before: Sequence[float]) -> np.ndarray:
    """``q_after * conj(q_before)``: the rotation ``R_after R_before^T`` as a quaternion [x, y, z, w]."""
    x1, y1, z1, w1 = (float(c) for c in q_after)
    x2, y2, z2, w2 = (-float(q_before[0]), -float(q_before[1]), -float(q_before[2]), float(q_before[3]))
    return np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])


def rotation_from_first_deg(records: Sequence[HistoryRecord]) -> list[np.ndarray | None]:
    """Each record's rotation from the first record with a pose, ``Log(R R_first^T)`` in degrees."""
    first = next((r.q_xyzw for r in records if r.q_xyzw is not None), None)
    return [None if r.q_xyzw is None or first is None else _quaternion_log_deg(_quaternion_delta(r.q_xyzw, first))
            for r in records]


def _calibrations(records: Sequence[HistoryRecord], camera: str) -> list[HistoryRecord]:
    return [r for r in records if r.camera == camera and r.kind == "calibration" and r.t_m is not None
            and r.q_xyzw is not None and r.sigma3_position_mm is not None and r.sigma3_rotation_deg is not None]


def cameras_of(records: Sequence[HistoryRecord]) -> list[str]:
    return list(dict.fromkeys(r.camera for r in records))


def flag_changes(records: Sequence[HistoryRecord]) -> list[Change]:
    """The changes between consecutive calibrations of each camera beyond their combined 3-sigma (any axis)."""
    changes = []
    for camera in cameras_of(records):
        calibrations = _calibrations(records, camera)
        for before, after in zip(calibrations, calibrations[1:]):
            position = 1000.0 * (np.array(after.t_m) - np.array(before.t_m))
            rotation = _quaternion_log_deg(_quaternion_delta(after.q_xyzw, before.q_xyzw))  # type: ignore[arg-type]
            position_sigma3 = np.hypot(np.array(before.sigma3_position_mm), np.array(after.sigma3_position_mm))
            rotation_sigma3 = np.hypot(np.array(before.sigma3_rotation_deg), np.array(after.sigma3_rotation_deg))
            if np.any(np.abs(position) > position_sigma3) or np.any(np.abs(rotation) > rotation_sigma3):
                changes.append(Change(camera, before, after, tuple(position.tolist()), tuple(rotation.tolist()),
                                      tuple(position_sigma3.tolist()), tuple(rotation_sigma3.tolist())))
    return changes


def _time(record: HistoryRecord) -> str:
    return record.time.strftime("%Y-%m-%d %H:%M:%S UTC") if record.time is not None else "?"


def _numbers(values: Sequence[float] | None, scale: float = 1.0, digits: int = 2) -> str:
    return "–" if values is None else "[" + ", ".join(f"{scale * v:.{digits}f}" for v in values) + "]"


def history_lines(robot: str, records: Sequence[HistoryRecord], changes: Sequence[Change]) -> list[str]:
    """The printed history: one line per record, then the flagged changes."""
    if not records:
        return [f"robot {robot}: no records"]
    lines = [f"robot {robot}: {len(records)} record(s), camera(s) {', '.join(cameras_of(records))}",
             "  T_base_cam: position mm (base axes) and its 3-sigma; rotation: 3-sigma deg",
             f"  {'time (UTC)':19s} {'run':>5s} {'camera':12s} {'kind':12s} {'verdict':12s} "
             f"{'position mm':28s} {'3-sigma mm':22s} {'3-sigma deg':20s}"]
    for r in records:
        lines.append(f"  {_time(r)[:19]:19s} {r.run_id:5d} {r.camera[:12]:12s} {r.kind:12s} {(r.verdict or '–')[:12]:12s} "
                     f"{_numbers(r.t_m, 1000.0, 1):28s} {_numbers(r.sigma3_position_mm, 1.0, 1):22s} "
                     f"{_numbers(r.sigma3_rotation_deg):20s}")
    lines += [change.line() for change in changes]
    if not changes:
        lines.append("no change between consecutive calibrations beyond their combined 3-sigma")
    return lines


CSV_COLUMNS = ("time_utc", "run", "robot", "camera", "kind", "verdict", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw",
               "rx_from_first_deg", "ry_from_first_deg", "rz_from_first_deg", "sigma3_x_mm", "sigma3_y_mm",
               "sigma3_z_mm", "sigma3_rx_deg", "sigma3_ry_deg", "sigma3_rz_deg", "changed", "mirror_fg_version",
               "input_sha256", "host")


def history_csv(records: Sequence[HistoryRecord], changes: Sequence[Change]) -> str:
    """One CSV row per record (columns ``CSV_COLUMNS``); ``changed`` is 1 on a calibration flagged against the
    one before it."""
    flagged = {c.after.id for c in changes}
    rotations: dict[int, np.ndarray | None] = {}
    for camera in cameras_of(records):
        mine = [r for r in records if r.camera == camera]
        rotations.update(zip((r.id for r in mine), rotation_from_first_deg(mine)))
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for r in records:
        def cells(values, scale=1.0):  # noqa: ANN001, ANN202 - a tuple or None
            return [""] * 3 if values is None else [repr(scale * float(v)) for v in values]

        rotation = rotations.get(r.id)
        writer.writerow([r.time.isoformat() if r.time else "", r.run_id, r.robot, r.camera, r.kind, r.verdict or "",
                         *cells(r.t_m, 1000.0), *([""] * 4 if r.q_xyzw is None else [repr(v) for v in r.q_xyzw]),
                         *cells(None if rotation is None else rotation.tolist()), *cells(r.sigma3_position_mm),
                         *cells(r.sigma3_rotation_deg), int(r.id in flagged), r.mirror_fg_version,
                         r.input_sha256 or "", r.host or ""])
    return text.getvalue()


def _figure_camera(camera: str, records: Sequence[HistoryRecord], changes: Sequence[Change]):  # noqa: ANN202
    """Position (mm) and rotation from the first calibration (deg) of one camera over time: each axis with its
    3-sigma band, flagged calibrations ringed, verifications as vertical lines coloured by verdict."""
    from matplotlib.dates import AutoDateLocator, ConciseDateFormatter

    from mirror_fg.report.figures import new_figure

    mine = [r for r in records if r.camera == camera]
    calibrations = _calibrations(mine, camera)
    rotations = dict(zip((r.id for r in calibrations), rotation_from_first_deg(calibrations)))
    flagged = {(c.after.id, row, axis) for c in changes if c.camera == camera for row, (values, bounds) in
               enumerate(((c.position_mm, c.position_sigma3_mm), (c.rotation_deg, c.rotation_sigma3_deg)))
               for axis in range(3) if abs(values[axis]) > bounds[axis]}  # the axes that changed
    fig = new_figure(11.0, 5.2)
    axes = fig.subplots(2, 3, sharex=True)
    times = [r.time for r in calibrations]
    for column, name in enumerate(_AXES):
        rows = ((axes[0][column], [1000.0 * r.t_m[column] for r in calibrations],  # type: ignore[index]
                 [r.sigma3_position_mm[column] for r in calibrations], f"position {name} (mm)"),  # type: ignore[index]
                (axes[1][column], [float(rotations[r.id][column]) for r in calibrations],  # type: ignore[index]
                 [r.sigma3_rotation_deg[column] for r in calibrations], f"rotation {name} from first (deg)"))  # type: ignore[index]
        for row, (ax, values, sigma3, label) in enumerate(rows):
            v, s = np.array(values), np.array(sigma3)
            if len(times):
                ax.fill_between(times, v - s, v + s, color="#90caf9", alpha=0.45, linewidth=0, step=None,
                                label="3-sigma")
                ax.plot(times, v, "-o", color="#1565c0", markersize=3, linewidth=1, label="calibration")
                for r, y in zip(calibrations, v):
                    if r.verdict == "check":
                        ax.plot([r.time], [y], "x", color=VERDICT_COLOURS["check"], markersize=7)
                    if (r.id, row, column) in flagged:
                        ax.plot([r.time], [y], "o", markerfacecolor="none", markeredgecolor="#c62828",
                                markersize=10, markeredgewidth=1.5)
            for r in mine:
                if r.kind == "verification" and r.time is not None:
                    ax.axvline(r.time, color=VERDICT_COLOURS.get(r.verdict or "", "#777"), linewidth=1, alpha=0.8,
                               linestyle="--")
            ax.set_title(label, fontsize=9)
            ax.tick_params(labelsize=7)
            locator = AutoDateLocator()
            ax.xaxis.set_major_locator(locator)
            ax.xaxis.set_major_formatter(ConciseDateFormatter(locator))
    fig.suptitle(f"camera {camera}: T_base_cam over time", fontsize=10)
    return fig


def history_html(robot: str, records: Sequence[HistoryRecord], changes: Sequence[Change], source: str) -> str:
    """The history page: a verdict box (changes flagged or none), the legend, one figure per camera, the
    flagged changes and the table of records, in the report's style (``report.pages``)."""
    from mirror_fg.report.pages import Block, RenderedFigure, html_page

    cameras = cameras_of(records)
    blocks = [Block("table", rows=[("robot", robot), ("registry", source), ("records", str(len(records))),
                                   ("cameras", ", ".join(cameras) or "–"),
                                   ("calibrations", str(sum(r.kind == "calibration" for r in records))),
                                   ("verifications", str(sum(r.kind == "verification" for r in records)))])]
    if changes:
        blocks.append(Block("verdict", text=f"{len(changes)} change(s) beyond the combined 3-sigma of consecutive "
                            "calibrations", items=[c.line() for c in changes], good=False))
    else:
        blocks.append(Block("verdict", text="no change between consecutive calibrations beyond their combined "
                            "3-sigma", good=True))
    blocks.append(Block("note", text="Each camera's T_base_cam (base axes): position in mm, rotation as the rotation "
                        "vector from its first calibration in degrees; blue band: each calibration's 3-sigma; red "
                        "ring: an axis that changed beyond the combined 3-sigma of two consecutive calibrations; red x: a "
                        "calibration whose verdict says check; dashed lines: verifications (red moved, green not "
                        "moved, orange cannot tell)."))
    for camera in cameras:
        blocks.append(Block("h2", text=f"Camera {camera}"))
        blocks.append(Block("figure", figure=RenderedFigure(_figure_camera(camera, records, changes)),
                            text=f"camera {camera}: position and rotation over time with 3-sigma bands"))
    blocks.append(Block("h2", text="Records"))
    blocks.append(Block("pre", id="records", text="\n".join(history_lines(robot, records, changes)[1:])))
    return html_page(f"mirror-fg history: robot {robot}", blocks)
