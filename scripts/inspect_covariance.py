#!/usr/bin/env python
"""Inspect the uncertainty of a calibration result (mirror-fg/result@1).

Prints the 6x6 camera-to-base covariance (docs/formats.md: ``[dtheta (rad), dt (m)]``, camera axes) as standard
deviations and a correlation matrix, the 3-sigma bounds of every mirror placement and reconstruction
point, and names the least-constrained direction (the eigenvector of the smallest information, with
rotations weighed at ``--lever-arm`` metres). Draws a PNG of the correlation matrix and the 3-sigma
ellipses of the position ``t_cam_base`` in the camera's xy, xz and yz planes.

Usage: ``python scripts/inspect_covariance.py result.json [-o result_covariance.png]``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.result import load_result
from mirror_fg.solver.information.crb import AXIS_NAMES, WeakestDirection, weakest_direction
from mirror_fg.report.figures import correlation, draw_correlation

LABELS = ("θx", "θy", "θz", "tx", "ty", "tz")
PLANES = (("x", "y", 0, 1), ("x", "z", 0, 2), ("y", "z", 1, 2))


def covariance_of(result: dict, source: str = "result") -> np.ndarray:
    """The 6x6 ``covariance_cam_base`` of a result@1 dictionary; DatasetError when absent or malformed."""
    value = result.get("covariance_cam_base")
    if value is None:
        raise DatasetError(f"{source}: no covariance_cam_base (was the result computed without covariance?)")
    covariance = np.asarray(value, dtype=float)
    if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
        raise DatasetError(f"{source}: covariance_cam_base must be a finite 6x6 matrix")
    if np.any(np.diag(covariance) <= 0.0):
        raise DatasetError(f"{source}: covariance_cam_base has a non-positive variance on its diagonal")
    return covariance


def ellipse(covariance_2x2: np.ndarray, scale: float = 3.0, num: int = 200) -> np.ndarray:
    """Points (num, 2) of the ``scale``-sigma ellipse of a 2x2 covariance, centred at 0."""
    values, vectors = np.linalg.eigh(covariance_2x2)
    angle = np.linspace(0.0, 2.0 * np.pi, num)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return scale * circle * np.sqrt(np.maximum(values, 0.0)) @ vectors.T


def report(result: dict, lever_arm_m: float = 1.0, source: str = "result") -> tuple[str, WeakestDirection]:
    """The printed text, and the weakest direction. ``source`` names the file in errors."""
    covariance = covariance_of(result, source)
    sigma = np.sqrt(np.diag(covariance))
    lines = ["T_cam_base (Cp = R Bp + t; camera axes x right, y down, z forward), covariance in docs/formats.md's "
             "[dtheta, dt] (R_true = Exp(dtheta) R_est, t_true = t_est + dt):"]
    lines.append("  1-sigma  rotation [" + ", ".join(f"{np.degrees(s):.4f}" for s in sigma[:3]) + "] deg,  position ["
                 + ", ".join(f"{1000 * s:.3f}" for s in sigma[3:]) + "] mm")
    lines.append("  3-sigma  rotation [" + ", ".join(f"{np.degrees(3 * s):.4f}" for s in sigma[:3]) + "] deg,  position ["
                 + ", ".join(f"{3000 * s:.3f}" for s in sigma[3:]) + "] mm")
    lines.append("  correlation matrix:")
    rho = correlation(covariance)
    lines.append("        " + "".join(f"{label:>8}" for label in LABELS))
    for label, row in zip(LABELS, rho):
        lines.append(f"    {label:>4}" + "".join(f"{value:8.3f}" for value in row))
    strong = [(abs(rho[i, j]), i, j) for i in range(6) for j in range(i + 1, 6) if abs(rho[i, j]) >= 0.7]
    for value, i, j in sorted(strong, reverse=True):
        lines.append(f"  strongly correlated: {AXIS_NAMES[i]} and {AXIS_NAMES[j]} ({rho[i, j]:+.2f})")
    weakest = weakest_direction(covariance, lever_arm_m)
    lines.append(f"  least-constrained direction: {weakest.text}")
    lines.append("  eigenvector [θx·L, θy·L, θz·L, tx, ty, tz] = [" + ", ".join(f"{v:+.3f}" for v in weakest.vector) + "]")
    mirrors = result.get("mirrors") or []
    if mirrors:
        lines.append("mirror placements (mirror vector v, camera frame), 3-sigma mm:")
        for l in sorted({e["mirror"] for e in mirrors}):
            worst = [max(e["sigma3_mm"]) for e in mirrors if e["mirror"] == l and e.get("sigma3_mm") is not None]
            if worst:
                lines.append(f"  mirror {l}: {len(worst)} placement(s), worst-axis 3-sigma median {np.median(worst):.2f} mm, "
                             f"max {np.max(worst):.2f} mm")
        for entry in mirrors:
            s3 = entry.get("sigma3_mm")
            bounds = "n/a" if s3 is None else "[" + ", ".join(f"{x:.2f}" for x in s3) + "]"
            lines.append(f"  mirror {entry['mirror']} placement {entry['config']}: {bounds}")
    points = result.get("points") or {}
    if points:
        lines.append("reconstruction points (base frame), 3-sigma mm:")
        for name in sorted(points, key=_natural):
            s3 = points[name].get("sigma3_mm")
            bounds = "n/a" if s3 is None else "[" + ", ".join(f"{x:.2f}" for x in s3) + "]"
            lines.append(f"  {name}: {bounds}")
        with_bounds = {n: max(p["sigma3_mm"]) for n, p in points.items() if p.get("sigma3_mm") is not None}
        if with_bounds:
            worst = max(with_bounds, key=with_bounds.get)
            lines.append(f"  least-constrained point: {worst} ({with_bounds[worst]:.2f} mm 3-sigma, worst axis)")
    return "\n".join(lines), weakest


def _natural(name: str):
    digits = "".join(c for c in name if c.isdigit())
    return (name.rstrip("0123456789"), int(digits) if digits else -1, name)


def plot(result: dict, path: Path, title: str = "") -> None:
    """Correlation matrix and the 3-sigma position ellipses (mm) in the camera's xy, xz, yz planes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    covariance = covariance_of(result)
    rho = correlation(covariance)
    fig = plt.figure(figsize=(14, 4.0), layout="constrained")
    grid = fig.add_gridspec(1, 4, width_ratios=[1.3, 1, 1, 1])
    ax = fig.add_subplot(grid[0, 0])
    image = draw_correlation(ax, rho, LABELS, fontsize=7)
    ax.set_title("correlation of T_cam_base")
    fig.colorbar(image, ax=ax, shrink=0.8)
    position_mm = 1e6 * covariance[3:, 3:]  # m^2 -> mm^2
    limit = 1.1 * 3.0 * float(np.sqrt(np.max(np.diag(position_mm))))  # one scale for the three planes
    for k, (a, b, i, j) in enumerate(PLANES):
        ax = fig.add_subplot(grid[0, k + 1])
        block = position_mm[np.ix_([i, j], [i, j])]
        points = ellipse(block)
        ax.plot(points[:, 0], points[:, 1], color="tab:blue")
        ax.fill(points[:, 0], points[:, 1], color="tab:blue", alpha=0.15)
        ax.axhline(0, color="grey", lw=0.5)
        ax.axvline(0, color="grey", lw=0.5)
        ax.set_xlim(-limit, limit)
        ax.set_ylim(-limit, limit)
        ax.set_aspect("equal")
        ax.set_xlabel(f"t{a} (mm)")
        ax.set_ylabel(f"t{b} (mm)")
        ax.set_title(f"3σ position, camera {a}{b}-plane")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("result", type=Path, help="mirror-fg/result@1 file (JSON or YAML)")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help="PNG to write (default: <result stem>_covariance.png beside the result)")
    parser.add_argument("--lever-arm", type=float, default=1.0,
                        help="metres at which a rotation is weighed against a translation (default 1)")
    args = parser.parse_args(argv)
    try:
        result = load_result(args.result)
        text, _ = report(result, args.lever_arm, str(args.result))
    except DatasetError as error:
        print(f"inspect_covariance: error: {error}", file=sys.stderr)
        return 2
    print(text)
    output = args.output or args.result.with_name(args.result.stem + "_covariance.png")
    plot(result, output, title=str(args.result))
    print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
