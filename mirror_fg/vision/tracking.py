"""Point tracking through video frames or photo sequences: KLT, then refinement onto the feature.

Pixels follow OpenCV's convention (the centre of the top-left pixel is (0, 0)). Frames are 8-bit
grayscale arrays of one size, in order. Each step moves a point with pyramidal Lucas-Kanade
(cv2.calcOpticalFlowPyrLK) from its position in the previous frame, keeps it only when tracking back
lands within ``fb_threshold_px`` of where it started (Kalal et al.'s forward-backward error) and it
stays inside the image, then *refines* the KLT position onto the feature the track started on:

- ``corner`` (default): ``cv2.cornerSubPix`` (half window 4 px, i.e. 9 x 9) on the linearised frame
  (inverse sRGB, as :mod:`mirror_fg.vision.detect` does for tag corners);
- ``blob`` / ``dot`` (the same): intensity-weighted centroid of a dark or bright disc (polarity from the
  first frame) against the median of its window's border, on the linearised frame;
- ``template``: ``cv2.findTransformECC`` (affine) of the *first* frame's patch around the point,
  anchored to that frame (never chained frame to frame), the point being the patch's centre;
- ``klt``: no refinement.

Why: pyramidal LK's translation-only model is biased when the window's appearance changes (a scene
seen through a moving mirror), and chaining frame to frame integrates that bias into a drift of up to
~1 px over a loop; a refinement tied to the feature itself does not accumulate it.

A track is cut, with a reason, when KLT fails, the forward-backward check fails, the point leaves the
image, or the refinement fails (no corner, blob or template match within ``max_shift_px`` of KLT).

Noise: every refinement gives a per-frame standard deviation of its fit (pixels, per axis):
Foerstner's ``s^2 (sum g g^T)^-1`` for the corner (``s`` the RMS of ``g . (q - p)`` over the window),
the propagated background noise for the centroid, the Gauss-Newton ``s^2 (J^T J)^-1`` of the
photometric residual for the template. Such statistics miss the model's bias (a corner blurred and
gamma-encoded, a disc seen obliquely), so a track's sigma (:meth:`PointTracker.sigma`) adds a floor in
quadrature, :data:`TRACK_SIGMA_FLOOR_PX` per kind: ``sqrt(floor^2 + mean(s_frame^2))``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

__all__ = [
    "KLTParams",
    "RefineParams",
    "TrackSample",
    "Track",
    "PointTracker",
    "track_klt",
    "refine_point",
    "FEATURE_KINDS",
    "TRACK_SIGMA_FLOOR_PX",
    "SRGB_TO_LINEAR",
]

#: Feature kinds a track can follow (``dot`` is ``blob``; ``klt`` is no refinement).
FEATURE_KINDS = ("corner", "blob", "dot", "template", "klt")
#: Per-kind floor (pixels, per axis) of a track's sigma. Measured on six rendered one-mirror loops
#: (``scripts/render_scene.py``'s sequence, 54 frames; tests/test_tracking_refine.py): refined corners
#: sat a median 0.17-0.25 px and at most 0.39 px from the truth, the same way in every frame (a
#: blurred corner's tip pulls cornerSubPix inwards), blob centroids and templates a median <= 0.05 px;
#: plain KLT drifted to 0.57-0.87 px (1.37 px with a 31 px window). The bias is shared by
#: all frames, so averaging does not remove it: at 0.5 px the reconstructed points were within
#: 2.9 sigma per axis in all six scenes. Detected fiducials use the capture's ``pixel_sigma`` (0.5 px by
#: default); tracked points are never tighter.
TRACK_SIGMA_FLOOR_PX = {"corner": 0.5, "blob": 0.5, "dot": 0.5, "template": 0.5, "klt": 1.5}

#: Inverse sRGB transfer function, 8-bit code -> linear intensity on the same 0-255 scale.
_x = np.arange(256) / 255.0
SRGB_TO_LINEAR = (np.where(_x <= 0.04045, _x / 12.92, ((_x + 0.055) / 1.055) ** 2.4) * 255.0).astype(np.float32)
del _x


@dataclass(frozen=True)
class KLTParams:
    """Settings of :func:`track_klt`.

    ``win_size``: side of the search window (pixels, odd); ``max_level``: pyramid levels above the
    image; ``fb_threshold_px``: largest forward-backward error kept (pixels); ``iterations``/``epsilon``:
    Lucas-Kanade stopping criteria (pixels); ``min_eig``: smallest normalized minimum eigenvalue of the
    window's gradient matrix (textureless windows fail).
    """

    win_size: int = 21
    max_level: int = 3
    fb_threshold_px: float = 0.5
    iterations: int = 50
    epsilon: float = 1e-3
    min_eig: float = 1e-4


@dataclass(frozen=True)
class RefineParams:
    """Settings of :func:`refine_point`.

    ``max_shift_px``: farthest the refined pixel may lie from KLT's (farther: another feature, cut);
    ``corner_half_window``: cornerSubPix half window (pixels; 4 -> 9 x 9); ``corner_min_ratio``: smallest
    ratio of the window's structure-tensor eigenvalues (below: an edge or a flat patch, not a corner);
    ``blob_half_window``: half side of the centroid window (pixels; the disc and a ring of background
    must fit); ``blob_min_contrast``: smallest fraction of the first frame's disc contrast kept;
    ``template_half``: half side of the first-frame patch (pixels); ``template_margin``: search margin
    around it (pixels); ``template_min_correlation``: smallest ECC correlation kept.
    """

    max_shift_px: float = 1.5
    corner_half_window: int = 4
    corner_min_ratio: float = 0.05
    blob_half_window: int = 8
    blob_min_contrast: float = 0.3
    template_half: int = 10
    template_margin: int = 4
    template_min_correlation: float = 0.9


@dataclass
class TrackSample:
    """One frame of a track: ``frame`` index, ``raw`` KLT pixel (None where the point was set, not
    tracked), ``refined`` pixel (the track's position), ``residual_px`` (the refinement's fit standard
    deviation, pixels per axis; None where not refined)."""

    frame: int
    raw: np.ndarray | None
    refined: np.ndarray
    residual_px: float | None = None

    @property
    def shift_px(self) -> float:
        """Distance the refinement moved KLT's pixel (0 where not tracked)."""
        return 0.0 if self.raw is None else float(np.linalg.norm(self.refined - self.raw))


@dataclass
class Track:
    """A followed point: its feature ``kind``, the anchor frame's ``template`` (linear patch) and
    ``anchor`` pixel, the blob ``polarity`` (+1 bright, -1 dark) and ``contrast``, the template's last
    affine map (initial guess only), and the ``history`` of :class:`TrackSample`."""

    name: str
    kind: str
    anchor: np.ndarray
    template: np.ndarray | None = None
    polarity: float = 1.0
    contrast: float = 0.0
    affine: np.ndarray = field(default_factory=lambda: np.eye(2))
    history: list[TrackSample] = field(default_factory=list)

    @property
    def pixel(self) -> np.ndarray:
        return self.history[-1].refined

    def sigma(self) -> float:
        """The track's pixel sigma (per axis): the kind's floor and the fits' RMS, in quadrature."""
        fits = [s.residual_px for s in self.history if s.residual_px is not None]
        spread2 = float(np.mean(np.square(fits))) if fits else 0.0
        return float(np.sqrt(TRACK_SIGMA_FLOOR_PX[self.kind] ** 2 + spread2))


def _klt(prev: np.ndarray, nxt: np.ndarray, pts: np.ndarray, params: KLTParams) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """track_klt with a reason per track ('' where kept)."""
    pts = np.asarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    n = pts.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool), []
    kwargs: dict[str, Any] = dict(
        winSize=(params.win_size, params.win_size),
        maxLevel=params.max_level,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon),
        minEigThreshold=params.min_eig,
    )
    # OpenCV's stubs want a Mat for the output argument that None leaves to OpenCV
    fwd, st_f, _ = cv2.calcOpticalFlowPyrLK(prev, nxt, pts, None, **kwargs)  # type: ignore[call-overload]
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(nxt, prev, fwd, None, **kwargs)  # type: ignore[call-overload]
    fwd = fwd.reshape(n, 2).astype(np.float64)
    fb_error = np.linalg.norm(back.reshape(n, 2) - pts.reshape(n, 2), axis=1)
    h, w = nxt.shape[:2]
    inside = (fwd[:, 0] >= 0) & (fwd[:, 1] >= 0) & (fwd[:, 0] <= w - 1) & (fwd[:, 1] <= h - 1)
    reasons = []
    for i in range(n):
        if st_f[i, 0] != 1 or st_b[i, 0] != 1:
            reasons.append("KLT lost the point (textureless window, or it left the image)")
        elif not fb_error[i] <= params.fb_threshold_px:
            reasons.append(f"forward-backward error {fb_error[i]:.2f} px > {params.fb_threshold_px} px")
        elif not inside[i]:
            reasons.append("left the image")
        else:
            reasons.append("")
    return fwd, np.array([r == "" for r in reasons]), reasons


def track_klt(
    prev: np.ndarray, nxt: np.ndarray, points: np.ndarray, params: KLTParams = KLTParams()
) -> tuple[np.ndarray, np.ndarray]:
    """Follow ``points`` (N, 2) from frame ``prev`` into frame ``nxt``.

    Returns the new positions (N, 2) (pixels; meaningful only where kept) and a boolean mask (N,) of the
    tracks that passed the forward-backward check and stayed inside ``nxt``.
    """
    fwd, ok, _ = _klt(prev, nxt, points, params)
    return fwd, ok


# --------------------------------------------------------------------------------------------------
# Refinement onto the feature (all on the linearised frame, float32)
# --------------------------------------------------------------------------------------------------


class RefineError(Exception):
    """The refinement found no feature of the track's kind near KLT's pixel (the message says why)."""


def _patch(image: np.ndarray, centre: np.ndarray, half: int) -> np.ndarray:
    """(2 half + 1)^2 float32 patch centred on the sub-pixel ``centre`` (bilinear, border replicated)."""
    side = 2 * half + 1
    return cv2.getRectSubPix(image, (side, side), (float(centre[0]), float(centre[1])))


def _gradients(patch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = cv2.Sobel(patch, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(patch, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return gx[1:-1, 1:-1], gy[1:-1, 1:-1]


def _sigma_from_normal(s2: float, N: np.ndarray) -> float:
    """Per-axis standard deviation sqrt(trace(s^2 N^-1) / 2) (pixels); inf when N is singular."""
    try:
        return float(np.sqrt(max(s2, 0.0) * np.trace(np.linalg.inv(N)) / 2))
    except np.linalg.LinAlgError:
        return float("inf")


def _refine_corner(linear: np.ndarray, start: np.ndarray, p: RefineParams) -> tuple[np.ndarray, float]:
    half = p.corner_half_window
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 1e-3)
    q = cv2.cornerSubPix(linear, start.reshape(1, 1, 2).astype(np.float32), (half, half), (-1, -1), criteria)
    q = q.reshape(2).astype(np.float64)
    # Foerstner: q solves sum_i G_i (q - p_i) = 0 with G_i = g_i g_i^T over the window (Gaussian weights)
    gx, gy = _gradients(_patch(linear, q, half + 1))
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    dx, dy = np.meshgrid(offsets, offsets)  # p_i - q
    w = np.exp(-(dx**2 + dy**2) / (2 * (half / 2.0 + 0.5) ** 2))
    gx, gy = gx.astype(np.float64), gy.astype(np.float64)
    N = np.array([[np.sum(w * gx * gx), np.sum(w * gx * gy)], [np.sum(w * gx * gy), np.sum(w * gy * gy)]])
    eig = np.linalg.eigvalsh(N)
    if eig[1] <= 0 or eig[0] / eig[1] < p.corner_min_ratio:
        raise RefineError(f"no corner (structure-tensor eigenvalue ratio {max(eig[0], 0) / max(eig[1], 1e-12):.3f} < {p.corner_min_ratio})")
    r = gx * dx + gy * dy  # g_i . (p_i - q): zero for every pixel of an ideal corner
    return q, _sigma_from_normal(float(np.sum(w * r**2)) / (w.size - 2), N)


def _blob_centroid(linear: np.ndarray, start: np.ndarray, polarity: float, half: int) -> tuple[np.ndarray, float, float]:
    """Iterated intensity-weighted centroid: (centre, contrast, per-axis sigma px)."""
    h, w = linear.shape[:2]
    c = np.asarray(start, dtype=np.float64).copy()
    for _ in range(10):
        ix, iy = int(round(c[0])), int(round(c[1]))
        if ix - half < 0 or iy - half < 0 or ix + half > w - 1 or iy + half > h - 1:
            raise RefineError("the blob's window left the image")
        patch = linear[iy - half : iy + half + 1, ix - half : ix + half + 1].astype(np.float64)
        border = np.concatenate([patch[0], patch[-1], patch[1:-1, 0], patch[1:-1, -1]])
        background = float(np.median(border))
        signal = polarity * (patch - background)
        contrast = float(signal.max())
        weights = np.clip(signal - 0.1 * contrast, 0.0, None)  # soft threshold: background texture out
        total = float(weights.sum())
        if contrast <= 0 or total <= 0:
            raise RefineError("no blob of the first frame's polarity in the window")
        ys, xs = np.mgrid[iy - half : iy + half + 1, ix - half : ix + half + 1]
        new = np.array([np.sum(weights * xs), np.sum(weights * ys)]) / total
        moved = float(np.linalg.norm(new - c))
        c = new
        if moved < 1e-3:
            break
    noise = 1.4826 * float(np.median(np.abs(border - background)))  # MAD of the background ring
    on = weights > 0
    spread = float(np.sum(((xs - c[0]) ** 2 + (ys - c[1]) ** 2)[on]) / 2)
    return c, contrast, noise * np.sqrt(spread) / total


def _refine_template(linear: np.ndarray, start: np.ndarray, track: Track, p: RefineParams) -> tuple[np.ndarray, float]:
    assert track.template is not None
    half, big = p.template_half, p.template_half + p.template_margin
    crop = _patch(linear, start, big)  # crop pixel (big, big) is ``start``
    warp = np.zeros((2, 3), np.float32)
    warp[:, :2] = track.affine
    warp[:, 2] = np.array([big, big]) - track.affine @ np.array([half, half])
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        rho, warp = cv2.findTransformECC(track.template, crop, warp, cv2.MOTION_AFFINE, criteria, None, 3)  # type: ignore[call-overload]  # OpenCV's stubs want a Mat for the optional mask
    except cv2.error as exc:
        raise RefineError(f"template match did not converge ({str(exc).strip().splitlines()[-1][:80]})") from None
    if not rho >= p.template_min_correlation:
        raise RefineError(f"template correlation {rho:.3f} < {p.template_min_correlation}")
    L = warp[:, :2].astype(np.float64)
    centre = L @ np.array([half, half]) + warp[:, 2]
    q = np.asarray(start, dtype=np.float64) + centre - big
    # Gauss-Newton covariance of the shift: s^2 (J^T J)^-1, J the gradients of the warped input.
    side = 2 * half + 1
    warped = cv2.warpAffine(crop, warp, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP).astype(np.float64)
    T = track.template.astype(np.float64).ravel()
    design = np.column_stack([T, np.ones_like(T)])
    coef, *_ = np.linalg.lstsq(design, warped.ravel(), rcond=None)
    s2 = float(np.sum((warped.ravel() - design @ coef) ** 2)) / (T.size - 8)
    gx, gy = _gradients(cv2.copyMakeBorder(warped.astype(np.float32), 1, 1, 1, 1, cv2.BORDER_REPLICATE))
    N = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]], dtype=np.float64)
    sigma_template = _sigma_from_normal(s2, N)
    track.affine = L
    return q, sigma_template * float(np.sqrt(max(np.linalg.eigvalsh(L @ L.T)[1], 0.0)))


def refine_point(linear: np.ndarray, raw: np.ndarray, track: Track, params: RefineParams = RefineParams()) -> tuple[np.ndarray, float | None]:
    """Move KLT's pixel ``raw`` onto ``track``'s feature in the linearised frame ``linear`` (float32).

    Returns ``(pixel, residual_px)`` (the fit's per-axis standard deviation, None for ``klt``); raises
    :class:`RefineError` with the reason when no such feature is within ``max_shift_px``.
    """
    raw = np.asarray(raw, dtype=np.float64)
    if track.kind == "klt":
        return raw, None
    if track.kind == "corner":
        q, sigma = _refine_corner(linear, raw, params)
    elif track.kind in ("blob", "dot"):
        q, contrast, sigma = _blob_centroid(linear, raw, track.polarity, params.blob_half_window)
        if contrast < params.blob_min_contrast * track.contrast:
            raise RefineError(f"blob contrast {contrast:.1f} below {params.blob_min_contrast:.0%} of the first frame's {track.contrast:.1f}")
    else:
        q, sigma = _refine_template(linear, raw, track, params)
    shift = float(np.linalg.norm(q - raw))
    if not shift <= params.max_shift_px:
        raise RefineError(f"refined {track.kind} {shift:.2f} px from KLT's pixel > {params.max_shift_px} px")
    h, w = linear.shape[:2]
    if not (0 <= q[0] <= w - 1 and 0 <= q[1] <= h - 1):
        raise RefineError("the refined pixel left the image")
    return q, sigma


# --------------------------------------------------------------------------------------------------
# The tracker
# --------------------------------------------------------------------------------------------------


@dataclass
class PointTracker:
    """Named points followed frame to frame, each kept on its feature.

    ``points`` maps a name to its pixel in the last frame given to :meth:`step`. :meth:`set` places or
    re-places a point (a fresh detection, or a track's start), :meth:`step` moves every point into the
    next frame (KLT, forward-backward check, refinement by the track's kind) and cuts those that fail,
    with the reason in ``cut``; :meth:`reset` forgets all (a gap in the frames). ``tracks`` keeps each
    point's kind, first-frame template and history; :meth:`sigma` is its pixel sigma.

    ``default_kind``: the kind of points :meth:`set` without one (``corner``; ``klt`` is the tracker
    without refinement); ``image_gamma``: ``srgb`` (frames are gamma-encoded, refinement runs on
    their inverse) or ``linear``.
    """

    params: KLTParams = field(default_factory=KLTParams)
    points: dict[str, np.ndarray] = field(default_factory=dict)
    refine: RefineParams = field(default_factory=RefineParams)
    default_kind: str = "corner"
    image_gamma: str = "srgb"
    tracks: dict[str, Track] = field(default_factory=dict)
    cut: dict[str, str] = field(default_factory=dict)
    frame: int = -1
    _prev: np.ndarray | None = field(default=None, repr=False)
    _linear: np.ndarray | None = field(default=None, repr=False)
    _pending: dict[str, bool] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        _check_kind(self.default_kind)
        if self.image_gamma not in ("srgb", "linear"):
            raise ValueError(f"image_gamma must be 'srgb' or 'linear', not {self.image_gamma!r}")

    def reset(self) -> None:
        self.points.clear()
        self.tracks.clear()
        self._pending.clear()
        self._prev = self._linear = None

    def linearise(self, gray: np.ndarray) -> np.ndarray:
        """The frame as linear intensity (float32, 0-255) on which refinements run."""
        return SRGB_TO_LINEAR[gray] if self.image_gamma == "srgb" else gray.astype(np.float32)

    def set(self, name: str, pixel: np.ndarray, kind: str | None = None, snap: bool = False) -> None:
        """Place ``name`` at ``pixel`` in the last frame stepped (or the next one, before any).

        ``kind``: the feature (:data:`FEATURE_KINDS`; default ``default_kind``); the track is anchored
        here (template, blob polarity). ``snap``: refine the given pixel onto the feature first (a
        hand-clicked start); otherwise it is kept as given (a detection).
        """
        kind = _check_kind(kind or self.default_kind)
        track = Track(name, kind, np.asarray(pixel, dtype=np.float64).copy())
        old = self.tracks.get(name)
        if old is not None and old.kind == kind:
            track.history = old.history
        self.tracks[name] = track
        self.cut.pop(name, None)
        self.points[name] = track.anchor.copy()
        if self._linear is None:
            self._pending[name] = snap  # anchored on the first frame stepped
        else:
            self._anchor(track, snap)

    def _anchor(self, track: Track, snap: bool) -> None:
        """Take ``track``'s first-frame data (blob polarity and contrast, template) from the last frame."""
        assert self._linear is not None
        linear, p = self._linear, self.refine
        if track.kind in ("blob", "dot"):
            inside = _patch(linear, track.anchor, 1)
            ring = _patch(linear, track.anchor, p.blob_half_window)
            track.polarity = 1.0 if float(np.mean(inside)) >= float(np.median(ring)) else -1.0
        if snap and track.kind not in ("template", "klt"):  # a template is its own feature
            try:
                track.anchor, _ = refine_point(linear, track.anchor, track, p)
            except RefineError:
                pass  # kept as given; the next step's refinement decides
            self.points[track.name] = track.anchor.copy()
        if track.kind in ("blob", "dot"):
            try:
                _, track.contrast, _ = _blob_centroid(linear, track.anchor, track.polarity, p.blob_half_window)
            except RefineError:
                track.contrast = 0.0
        track.template = _patch(linear, track.anchor, p.template_half).copy()
        track.affine = np.eye(2)
        track.history.append(TrackSample(self.frame, None, track.anchor.copy()))

    def step(self, frame: np.ndarray, index: int | None = None) -> list[str]:
        """Track every point into ``frame`` (grayscale); return the names dropped (reasons in ``cut``).

        ``index``: the frame's number in the video or sequence (default: one more than the last).
        """
        self.frame = self.frame + 1 if index is None else int(index)
        linear = self.linearise(frame)
        dropped: list[str] = []
        if self._prev is not None and self.points:
            names = list(self.points)
            new, ok, reasons = _klt(self._prev, frame, np.array([self.points[n] for n in names]), self.params)
            for name, raw, good, why in zip(names, new, ok, reasons):
                track = self.tracks[name]
                if good:
                    try:
                        q, residual = refine_point(linear, raw, track, self.refine)
                    except RefineError as exc:
                        good, why = False, str(exc)
                if not good:
                    del self.points[name]
                    self.cut[name] = f"frame {self.frame}: {why}"
                    dropped.append(name)
                    continue
                self.points[name] = q
                track.history.append(TrackSample(self.frame, raw.copy(), q.copy(), residual))
        self._prev, self._linear = frame, linear
        for name, snap in self._pending.items():  # points set before the first frame anchor on it
            if name in self.tracks:
                self._anchor(self.tracks[name], snap)
        self._pending.clear()
        return dropped

    def sigma(self, name: str) -> float:
        """Pixel sigma (per axis) of ``name``'s track: see the module docstring."""
        return self.tracks[name].sigma()

    def history(self, name: str) -> list[TrackSample]:
        return self.tracks[name].history


def _check_kind(kind: str) -> str:
    if kind not in FEATURE_KINDS:
        raise ValueError(f"feature kind {kind!r} is not one of {', '.join(FEATURE_KINDS)}")
    return kind
