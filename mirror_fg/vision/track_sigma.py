"""Each tracked point's pixel sigma for dataset@1's ``point_sigma``, from a capture's ``track:``.

A tracked point's pixel is noisier, and biased along its track, compared with a detected fiducial's
corner (:mod:`mirror_fg.vision.tracking`); weighed with the one ``pixel_sigma`` its reconstructed
position's covariance would not cover what the tracker does. ``detect`` writes, for every ``track:``
point that some kept image observes: the entry's ``sigma`` where the user gave one, else the tracker's
(:meth:`~mirror_fg.vision.tracking.Track.sigma`: the feature kind's floor and the refinement's fit
RMS in quadrature; the kind's floor alone when the track was lost to a gap in the frames), never
below the capture's ``pixel_sigma`` (a tracked point is never tighter than a detected fiducial).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping

from mirror_fg.io.capture import Capture
from mirror_fg.vision.tracking import TRACK_SIGMA_FLOOR_PX, Track

__all__ = ["tracked_point_sigma"]


def tracked_point_sigma(capture: Capture, tracks: Mapping[str, Track], observed: Iterable[str]) -> dict[str, float]:
    """``{name: sigma (pixels, per axis)}`` of the ``track:`` points of ``capture`` among ``observed``
    (the names the kept images hold), in ``track:`` order. ``tracks``: the tracker's
    (:attr:`~mirror_fg.vision.tracking.PointTracker.tracks`) after the last image."""
    seen = set(observed)
    sigmas: dict[str, float] = {}
    for name, start in capture.track.items():
        if name not in seen:
            continue
        if start.sigma is not None:
            sigmas[name] = float(start.sigma)
            continue
        track = tracks.get(name)
        sigma = track.sigma() if track is not None else TRACK_SIGMA_FLOOR_PX.get(start.feature, TRACK_SIGMA_FLOOR_PX["klt"])
        sigmas[name] = max(float(sigma), float(capture.pixel_sigma))
    return sigmas
