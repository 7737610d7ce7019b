"""The vectorised reflection model (eqs. 3-9) and the arrays it runs on, shared by the stacked factors
(``batched.py``) and the factors that eliminate the last mirror's placements (``eliminated.py``).

Frames and tangents as ``core/geometry.py``: ``T_cam_base`` perturbed in GTSAM's Pose3 tangent
``[w, nu]``; mirror vectors in the camera frame, metres; points in the base frame, metres.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from reference.stacking import Fiducials, KeyLayout, Observation

__all__ = ["reflection_model", "measurement_arrays", "mirror_input", "last_mirror_moments"]


def reflection_model(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    base_T: np.ndarray,
    landmark_index: np.ndarray,
    landmark_point_rows: np.ndarray,
    mirror_rows: np.ndarray,
    observed_T: np.ndarray,
    jacobians: bool,
    levels: Sequence[int] | None = None,
) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    """Residuals ``h - z`` (2, M) of M measurements (eqs. 2, 3, 5-9) and, when asked, their Jacobians.

    Structure of arrays: a point is (3, M), a 2x3 Jacobian per measurement is (2, 3, M), so every numpy
    operation runs over all M measurements on contiguous rows. R, t: ``T_cam_base``; P: (K, 3) rows of
    mirror vectors and landmarks; base_T: (3, M) base-frame points (fiducials; landmark columns are
    taken from P at ``landmark_point_rows``); mirror_rows: (Nv, M) row of P of each mirror.
    Returns ``(residual, B, blocks)``: B the (3, M) base points used; blocks ``(cross, GR, mirror)``:
    the pose Jacobian's rotation (2, 3, M) and translation / landmark (2, 3, M) parts and
    ``{level: (2, 3, M)}`` per mirror level (only ``levels`` when given, mirror 1 = level 0; then the
    pose parts are None).
    """
    PT = np.ascontiguousarray(P.T)  # (3, num points)
    B = base_T
    if len(landmark_index):
        B = B.copy()
        B[:, landmark_index] = np.take(PT, landmark_point_rows, axis=1)
    x = R @ B
    x += t[:, None]  # eq. (2), (3, M)
    num_mirrors = mirror_rows.shape[0]
    before, vectors, vvs, vxs = [], [], [], []
    for level in range(num_mirrors):
        v = np.take(PT, mirror_rows[level], axis=1)
        vv = np.einsum("im,im->m", v, v)
        vx = np.einsum("im,im->m", v, x)
        before.append(x)
        vectors.append(v)
        vvs.append(vv)
        vxs.append(vx)
        scale = vx - vv
        scale *= 2.0
        scale /= vv
        x = x - v * scale  # eq. (3): M x + 2 v
    inv_depth = 1.0 / x[2]
    residual = x[:2] * inv_depth
    residual -= observed_T  # eq. (9), h - z, (2, M)
    if not jacobians:
        return residual, B, None
    # d z / d x (eq. 9), then back through the mirrors: G <- G M_k (eq. 3). Blocks are (2, 3, M).
    G = np.zeros((2, 3, x.shape[1]))
    G[0, 0] = inv_depth
    G[1, 1] = inv_depth
    inv_depth *= inv_depth
    np.multiply(x[:2], inv_depth, out=G[:, 2])
    G[:, 2] *= -1.0
    mirror_blocks = {}
    work = np.empty_like(G)
    lowest = 0 if levels is None else min(levels)
    for level in range(num_mirrors - 1, lowest - 1, -1):
        v, xb, vv, vx = vectors[level], before[level], vvs[level], vxs[level]
        Gv = np.einsum("ijm,jm->im", G, v)[:, None, :]  # (2, 1, M)
        two_over_vv = 2.0 / vv
        # G (2I - 2[(vx/vv) I + v x^T/vv - 2 vx v v^T/vv^2]) = G d(M x + 2v)/dv at x = xb.
        H = G * (2.0 - vx * two_over_vv)
        np.multiply(Gv, xb * two_over_vv, out=work)
        H -= work
        np.multiply(Gv, v * (2.0 * vx * two_over_vv / vv), out=work)
        H += work
        if levels is None or level in levels:
            mirror_blocks[level] = H
        if levels is not None and level == lowest:
            return residual, B, (None, None, mirror_blocks)
        np.multiply(Gv, v * two_over_vv, out=work)
        G -= work  # G M_k
    GR = np.matmul(R.T, G)  # d z / d Bp, (2, 3, M)
    cross = np.empty_like(GR)  # rows Bp x (GR row) = rows of -GR [Bp]x
    for c, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(B[a], GR[:, b], out=cross[:, c])
        cross[:, c] -= B[b] * GR[:, a]
    return residual, B, (cross, GR, mirror_blocks)


def mirror_input(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    base_T: np.ndarray,
    landmark_index: np.ndarray,
    landmark_point_rows: np.ndarray,
    mirror_rows: np.ndarray,
    level: int,
) -> np.ndarray:
    """The points (3, M) as they reach mirror ``level`` (mirror 1 = level 0): eq. (2), then eq. (3) for
    the mirrors below ``level``, with the same operations as :func:`reflection_model`. Arguments as there."""
    PT = np.ascontiguousarray(P.T)
    B = base_T
    if len(landmark_index):
        B = B.copy()
        B[:, landmark_index] = np.take(PT, landmark_point_rows, axis=1)
    x = R @ B
    x += t[:, None]
    for below in range(level):
        v = np.take(PT, mirror_rows[below], axis=1)
        vv = np.einsum("im,im->m", v, v)
        scale = np.einsum("im,im->m", v, x) - vv
        scale *= 2.0
        scale /= vv
        x = x - v * scale
    return x


#: Pairs (i, j) of the 4 columns ``[J_v | e]`` whose products :func:`last_mirror_moments` sums: the
#: 6 entries of ``J_v^T J_v`` (upper triangle, row-major), the 3 of ``J_v^T e`` and ``e^T e``.
_MOMENT_LEFT = np.array([0, 0, 0, 1, 1, 2, 0, 1, 2, 3], dtype=np.intp)
_MOMENT_RIGHT = np.array([0, 1, 2, 1, 2, 2, 3, 3, 3, 3], dtype=np.intp)


def last_mirror_moments(
    xb: np.ndarray, v: np.ndarray, observed_T: np.ndarray, whiten_T: np.ndarray, starts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The last mirror's reflection (eq. 3) and projection (eq. 9) of ``xb`` (3, M), the points as they
    reach it, in mirrors ``v`` (3, M), whitened by ``whiten_T`` (2, M): returns the whitened residuals
    (2, M) and, summed over the segments beginning at ``starts``, the moments (10, S) of ``[J_v | e]``
    (``J_v`` the whitened Jacobian of the residual in ``v``): rows 0-5 ``J_v^T J_v`` (00, 01, 02, 11,
    12, 22), rows 6-8 ``J_v^T e``, row 9 ``e^T e``. The same model as :func:`reflection_model`'s last
    level, with the Jacobian's zeros left out."""
    vv = np.einsum("im,im->m", v, v)
    vx = np.einsum("im,im->m", v, xb)
    scale = vx - vv
    scale *= 2.0
    scale /= vv
    x = xb - v * scale
    inv_depth = 1.0 / x[2]
    A = np.empty((2, 4, xb.shape[1]))  # [J_v | e] per residual row, whitened
    e = A[:, 3]
    np.multiply(x[:2], inv_depth, out=e)
    e -= observed_T
    # G = d z / d x (2, 3): [[d, 0, -x0 d^2], [0, d, -x1 d^2]], d = 1 / depth
    g2 = x[:2] * (inv_depth * inv_depth)
    g2 *= -1.0
    Gv = v[:2] * inv_depth
    Gv += g2 * v[2]  # (2, M): G v
    two_over_vv = 2.0 / vv
    a = 2.0 - vx * two_over_vv
    # H = G a - Gv (xb 2/vv)^T + Gv (v 4 vx / vv^2)^T = G a + Gv q^T
    q = v * (2.0 * vx * two_over_vv / vv)
    q -= xb * two_over_vv
    H = A[:, :3]
    np.multiply(Gv[:, None, :], q[None, :, :], out=H)
    diagonal = inv_depth * a
    H[0, 0] += diagonal
    H[1, 1] += diagonal
    H[:, 2] += g2 * a
    A *= whiten_T[:, None, :]
    products = np.take(A, _MOMENT_LEFT, axis=1)
    products *= np.take(A, _MOMENT_RIGHT, axis=1)
    moments = np.add.reduceat(products[0] + products[1], starts, axis=1)
    return e, moments


def measurement_arrays(
    dataset: Fiducials, layout: KeyLayout, measurements: Sequence[Observation]
) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measurements as arrays: ``(point_keys, mirror_rows (M, Nv), landmark_rows (M,), base_points
    (M, 3), observed (M, 2))``. Row r of the point array is key ``point_keys[r]``: the mirror
    configurations (sorted) then the landmarks (sorted by name); ``landmark_rows`` is -1 for a fiducial,
    whose base-frame point (metres) is in ``base_points``."""
    num_mirrors = len(measurements[0].mirror_configs)
    mirror_configs = sorted(layout.mirror_keys)
    row_of_config = {config: r for r, config in enumerate(mirror_configs)}
    point_names = sorted(layout.point_keys)
    row_of_point = {name: len(mirror_configs) + j for j, name in enumerate(point_names)}
    point_keys = [layout.mirror_keys[c] for c in mirror_configs] + [layout.point_keys[n] for n in point_names]

    count = len(measurements)
    mirror_rows = np.empty((count, num_mirrors), dtype=np.intp)
    landmark_rows = np.full(count, -1, dtype=np.intp)
    base_points = np.zeros((count, 3))
    observed = np.empty((count, 2))
    for i, meas in enumerate(measurements):
        if len(meas.mirror_configs) != num_mirrors:
            raise ValueError(
                f"image {meas.image_id!r}: {len(meas.mirror_configs)} mirror configurations, expected {num_mirrors}"
            )
        for l, m in enumerate(meas.mirror_configs):
            try:
                mirror_rows[i, l] = row_of_config[(l + 1, m)]
            except KeyError:
                raise ValueError(f"image {meas.image_id!r}: mirror {l + 1} placement {m} has no key in the layout") from None
        if meas.point in dataset.fiducials:
            base_points[i] = dataset.fiducials[meas.point]
        elif meas.point in row_of_point:
            landmark_rows[i] = row_of_point[meas.point]
        else:
            raise ValueError(f"image {meas.image_id!r}: point {meas.point!r} is neither a fiducial nor a layout point")
        observed[i] = meas.normalized
    return point_keys, mirror_rows, landmark_rows, base_points, observed
