"""The last reflection of a view in closed form, for the placement that ``view_eliminated.py`` eliminates
(Hesch et al., eqs. 3, 9, 23; the model of ``views.py``): with the points ``y`` as they reach the last
mirror (camera frame, metres; ``view_stack._Group.reflected_soa`` of the other reflections), the view's
prediction is one reflection ``x = y - 2 v (v.y / v.v - 1)`` (eq. 3) and the projection ``z = x_xy / x_z``
(eq. 9), ``v`` the eliminated placement's mirror vector (camera frame: its owner is the view's camera).

Why: the inner Gauss-Newton of the eliminated placements (``view_eliminated._solve``) evaluates its views
a few times per evaluation with everything but ``v`` held. The points before the last mirror do not
change meanwhile, so they are computed once per evaluation and each inner iteration is this reflection,
its derivative in ``v`` and the projection, elementwise over the views in a structure-of-arrays layout
((3, b, N) for b views of N points) as the tree's eliminated factor does (``tests/reference/eliminated.py``). The same
closed form linearises the kept unknowns (through ``dy``, the reflection's linear part
``M = I - 2 v v^T / v.v``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["last_reflection", "moments", "augmented_normals"]

#: :func:`moments` of at most this many residuals (2 N b) as one ``einsum`` over the rows; above it the
#: per-pair sums, whose cost grows slower (measured: 2x faster at b = 1, N = 3; even near 2 N b = 5,000).
SMALL_MOMENTS = 4096


def last_reflection(y: np.ndarray, v: np.ndarray, observed: np.ndarray, sigmas: np.ndarray):
    """``(x, z, e, A_v)`` of each view through its last mirror: the reflected points ``x`` (3, N, b), the
    predictions ``z`` (2, N, b), whitened residuals ``e = (z - observed) / sigmas`` (2, N, b) and their
    whitened derivative in ``v`` ``A_v`` (2, 3, N, b). ``y``: the points before the mirror (3, N, b);
    ``v``: each view's mirror vector (b, 3); ``observed``, ``sigmas``: (2, N, b)."""
    v = v.T  # (3, b)
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]  # (b,)
    vy = v[0] * y[0] + v[1] * y[1] + v[2] * y[2]  # (N, b)
    s = vy / vv - 1.0
    x = y - 2.0 * v[:, None, :] * s[None]  # eq. (3): M y + 2 v
    inverse_depth = 1.0 / x[2]
    z = x[:2] * inverse_depth  # eq. (9)
    e = (z - observed) / sigmas
    # ds/dv_j = y_j / v.v - 2 v_j (v.y) / (v.v)^2; dx_i/dv_j = -2 (delta_ij s + v_i ds_j);
    # dz_a/dv_j = (dx_a/dv_j - z_a dx_z/dv_j) / x_z
    ds = (y - 2.0 * (s + 1.0)[None] * v[:, None, :]) / vv  # (3, N, b)
    f = -2.0 * inverse_depth / sigmas  # (2, N, b)
    q = (v[:2, None, :] - z * v[2]) * f  # (2, N, b)
    A_v = q[:, None] * ds[None]  # (2, 3, N, b)
    for a in range(2):
        A_v[a, a] += f[a] * s
        A_v[a, 2] -= f[a] * s * z[a]
    return x, z, e, A_v


def moments(y: np.ndarray, v: np.ndarray, observed: np.ndarray, sigmas: np.ndarray):
    """Each view's ``A_v^T A_v`` (b, 3, 3), ``A_v^T e`` (b, 3) and ``e.e`` (b,) (:func:`last_reflection`):
    its share of its placement's Gauss-Newton system with the rest held."""
    _, _, e, A_v = last_reflection(y, v, observed, sigmas)
    if e.size <= SMALL_MOMENTS:  # few rows: one contraction (the per-pair sums below cost ten calls)
        rows = np.concatenate([A_v.transpose(1, 0, 2, 3), e[None]], axis=0)  # (4, 2, N, b)
        G = np.einsum("janb,kanb->bjk", rows, rows)
        return G[:, :3, :3], G[:, :3, 3], G[:, 3, 3]

    def dot(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # each view's sum over its rows (2, N, b) -> (b,)
        return (p[0] * q[0] + p[1] * q[1]).sum(axis=0)

    D = np.empty((e.shape[2], 3, 3))
    for j in range(3):
        for k in range(j, 3):
            D[:, j, k] = D[:, k, j] = dot(A_v[:, j], A_v[:, k])
    return D, np.stack([dot(A_v[:, j], e) for j in range(3)], axis=1), dot(e, e)


def augmented_normals(y: np.ndarray, dy: np.ndarray, v: np.ndarray, column: int, observed: np.ndarray,
                      sigmas: np.ndarray, work: dict | None = None) -> np.ndarray:
    """Each view's augmented normal matrix ``[A | e]^T [A | e]`` (b, P+1, P+1) in its local columns (the
    layout of ``views.ViewSlots``): ``dy`` (3, P, N, b) the derivative of ``y`` in the local columns (zero
    in the eliminated placement's), ``column`` the first of the eliminated placement's three columns (its
    variable is ``v`` itself). ``work``: buffers kept between calls (a dict, filled here; the result is one
    of them, valid until the next call): a fresh array of this size per call costs its pages again."""
    x, z, e, A_v = last_reflection(y, v, observed, sigmas)
    P, n, b = dy.shape[1:]
    work = {} if work is None else work
    if work.get("shape") != (P, n, b):
        work.update(shape=(P, n, b), rows=np.empty((P + 1, 2, n, b)), gram=np.empty((b, P + 1, P + 1)),
                    views_first=np.empty((b, P + 1, 2 * n)), vdy=np.empty((P, n, b)), dx_z=np.empty((P, n, b)),
                    tmp=np.empty((P, n, b)))
    vdy, dx_z, tmp, rows = work["vdy"], work["dx_z"], work["tmp"], work["rows"]
    v = v.T
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    np.multiply(v[0], dy[0], out=vdy)  # 2 v.dy / v.v (P, N, b)
    vdy += np.multiply(v[1], dy[1], out=tmp)
    vdy += np.multiply(v[2], dy[2], out=tmp)
    vdy *= 2.0 / vv
    np.subtract(dy[2], np.multiply(v[2], vdy, out=tmp), out=dx_z)  # M dy, its depth
    scale = 1.0 / (x[2][None] * sigmas)  # (2, N, b)
    for a in range(2):  # dz_a = (dx_a - z_a dx_z) / x_z, whitened, into [A | e]
        dz = rows[:P, a]
        np.subtract(dy[a], np.multiply(v[a], vdy, out=tmp), out=dz)  # dx_a = (M dy)_a
        dz -= np.multiply(z[a], dx_z, out=tmp)
        dz *= scale[a]
        rows[column:column + 3, a] = A_v[a]
        rows[P, a] = e[a]
    stacked = work["views_first"]  # (b, P+1, 2N): each view's rows last, for one product per view
    stacked[...] = rows.reshape(P + 1, 2 * n, b).transpose(2, 0, 1)
    return np.matmul(stacked, stacked.transpose(0, 2, 1), out=work["gram"])
