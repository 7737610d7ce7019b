"""``mirror-fg live --verify RESULT``: the verdict of ``verify`` (``analysis/verify.py``, docs/formats.md "Has it
moved?") as frames arrive: after each frame a live session adds (a new mirror placement), the placements
so far are tested against RESULT (an arm's session: its frames with their joint states, against an arm's
result, ``analysis/verify_arm.py``). Pixels as the session detected them; frames and units as verify's.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mirror_fg.core.errors import MirrorFgError
from mirror_fg.io.dataset import DATASET_FORMAT, dataset_from_dict
from mirror_fg.data import Dataset
from mirror_fg.analysis.verify import Verification, verify

__all__ = ["LiveVerifier"]


class LiveVerifier:
    """Tests a :class:`~mirror_fg.live.session.LiveSession`'s added placements against a stored result.

    ``update()`` after each added frame gives the :class:`Verification` of every placement so far (or None
    where they cannot be tested yet, with the reason in :attr:`waiting`); :attr:`last` is the latest."""

    def __init__(self, result: Mapping[str, Any], session: Any, *, alpha: float = 0.01, tolerance_mm: float = 2.0,
                 tolerance_deg: float = 0.2, source: str = "result"):
        self.result, self.session = result, session
        self.alpha, self.tolerance_mm, self.tolerance_deg, self.source = alpha, tolerance_mm, tolerance_deg, source
        self.last: Verification | None = None
        self.waiting = "no placement yet"

    def dataset(self) -> Dataset:
        """The session's added placements as a dataset@1 (one mirror, one placement per frame; an arm's
        session: its added frames with their joint states, ``LiveArmSession.dataset``)."""
        session = self.session
        if getattr(session.capture, "robot", None) is not None:
            return session.dataset()
        capture = session.capture
        return dataset_from_dict({
            "format": DATASET_FORMAT, "num_mirrors": 1, "camera": session.camera_dict,
            "pixel_sigma": capture.pixel_sigma,
            "fiducials": {n: [float(x) for x in p] for n, p in session.fiducials.items()},
            "images": [{"id": f"frame{a.frame:06d}", "mirror_configs": [k],
                        "observations": {n: [float(p[0]), float(p[1])] for n, p in a.points.items()}}
                       for k, a in enumerate(session.added)],
        }, f"{capture.source} (live)")

    def update(self) -> Verification | None:
        if not getattr(self.session, "added", None) and not getattr(self.session, "images", None):
            return None
        try:
            self.last = verify(self.result, self.dataset(), alpha=self.alpha, tolerance_mm=self.tolerance_mm,
                               tolerance_deg=self.tolerance_deg, source=self.source)
        except MirrorFgError as error:  # e.g. a placement that cannot be started yet: wait for the next frame
            self.waiting = str(error)
            return None
        return self.last
