#!/usr/bin/env python
"""Per-image latency of the incremental (iSAM2) calibration against re-running the batch solve.

Streams a simulated recording in order (default: the issue's 300 images, mirror 1 in three placements
of 100 images, mirror 2 new in every image, 10 reconstruction points, 1 px) through
``IncrementalCalibrator.add_image`` and prints:

* the image of the first estimate and what that start-up cost;
* the per-image update latency (median, p95, max) after start-up: over every image, and over the
  images of a *settled* calibrator (the start-up's LM solution was a clean minimum; before that each
  image re-runs the start-up, see ``mirror_fg.solver.incremental.calibrator``);
* the total time of the stream and of ``calibration(full=True)``, and how far the last per-image and
  the full estimate are from the batch MLE (per pose axis, in batch standard deviations);
* the time a batch solve (``mirror_fg.calibrate``) re-run after every image from the first estimate on
  would take: timed at ``--batch-samples`` image counts and interpolated between them (trapezoids),
  unless ``--batch-every-image`` times every one.

Example: ``python scripts/benchmark_incremental.py`` (about a minute; a few with --batch-every-image).
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from mirror_fg import calibrate
from mirror_fg.data import Dataset
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator
from mirror_fg.solver.information.crb import pose_error
from mirror_fg.simulate.tree import simulate_base_case


def pose_sigmas(batch, estimate) -> np.ndarray:
    """Per-axis ``|estimate - batch| / sigma_batch`` in docs/formats.md's ``[dtheta, dt]``."""
    difference = pose_error(estimate.R_cam_base, estimate.t_cam_base, batch.R_cam_base, batch.t_cam_base)
    return np.abs(difference) / np.sqrt(np.diag(batch.covariance))


def stats_ms(seconds: list[float]) -> str:
    if not seconds:
        return "n=0"
    ms = 1000.0 * np.asarray(seconds)
    return (f"median {np.median(ms):7.1f} ms, p95 {np.percentile(ms, 95):7.1f} ms, max {ms.max():7.1f} ms "
            f"(n={len(ms)}, > 100 ms: {int(np.sum(ms > 100))})")


def latency_mode(counts: list[int], placements: int, sigma: float, seed: int) -> dict[int, dict[str, float]]:
    """``--latency``: ``add_image`` p50 / p95 / max over a stream of each length (2 mirrors, 3 fiducials, no
    points), after the first estimate; each stream simulated at its own length. Also: restarts after the
    first estimate, the time of ``calibration(full=True)`` at the end and how far the last per-image
    estimate is from it (largest pose axis, in its standard deviations): what the relinearisation
    thresholds cost in accuracy."""
    figures = {}
    print(f"add_image latency (ms) after the first estimate; {placements} placements of mirror 1, {sigma} px, "
          f"seed {seed}; load average {os.getloadavg()[0]:.2f}")
    print(f"{'images':>8s} {'p50':>8s} {'p95':>8s} {'max':>8s} {'p50 last 10%':>13s} {'p95 last 10%':>13s} {'stream s':>9s} "
          f"{'restarts':>8s} {'full s':>7s} {'last vs full':>12s}")
    for count in counts:
        ds, _ = simulate_base_case(num_images=count, num_points=0, pixel_sigma=sigma, mirror1_placements=placements,
                                   seed=seed)
        calibrator = IncrementalCalibrator(ds)
        latency, first, estimate, restarts_at_first = [], None, None, 0
        stream_start = time.perf_counter()
        for n, image in enumerate(ds.images, start=1):
            start = time.perf_counter()
            estimate = calibrator.add_image(image)
            latency.append(time.perf_counter() - start)
            if estimate is not None and first is None:
                first, restarts_at_first = n, calibrator.restarts
        total = time.perf_counter() - stream_start
        if first is None:
            print(f"{count:8d}  the stream never allowed the analytical solution")
            continue
        after = np.array(latency[first:]) * 1e3
        tail = after[-max(1, len(after) // 10):]
        start = time.perf_counter()
        full = calibrator.calibration(full=True)
        full_s = time.perf_counter() - start
        row = {"p50": float(np.percentile(after, 50)), "p95": float(np.percentile(after, 95)), "max": float(after.max()),
               "p50_tail": float(np.percentile(tail, 50)), "p95_tail": float(np.percentile(tail, 95)), "stream_s": total,
               "restarts": calibrator.restarts - restarts_at_first, "full_s": full_s,
               "last_vs_full_sigmas": float(pose_sigmas(full, estimate).max())}
        figures[count] = row
        print(f"{count:8d} {row['p50']:8.2f} {row['p95']:8.2f} {row['max']:8.1f} {row['p50_tail']:13.2f} "
              f"{row['p95_tail']:13.2f} {total:9.1f} {row['restarts']:8d} {full_s:7.2f} "
              f"{row['last_vs_full_sigmas']:9.3f} sd", flush=True)
    return figures


def rig_mode(shared: int, own: int, seed: int) -> None:
    """The general view model's stream: a three-camera rig with two hand-held mirrors (``simulate --kind
    mixed --cameras 3 --shared K --own N,N,N``) in file order; per-image update latency after the start,
    and the median of the last 100 updates against the first 100 (does an update cost grow with the
    images in the graph?)."""
    from mirror_fg.simulate.rig import simulate_rig_mixed

    from mirror_fg.io.dataset import dataset_from_dict

    ds = dataset_from_dict(simulate_rig_mixed(3, own=[own] * 3, shared=shared, seed=seed)[0])
    calibrator = IncrementalCalibrator(ds)
    latency, cpu, first = [], [], None
    for n, image in enumerate(ds.images, start=1):
        start, start_cpu = time.perf_counter(), time.process_time()
        estimate = calibrator.add_image(image)
        if estimate is not None:
            if first is None:
                first = n
            else:
                latency.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
    if first is None:
        raise SystemExit("the rig stream never started")
    ms = np.asarray(latency) * 1e3
    print(f"rig stream: {len(ds.images)} images, 3 cameras; first estimate at image {first}")
    print(f"  per image after the start   median {np.median(ms):6.1f} ms   p95 {np.percentile(ms, 95):6.1f} ms   "
          f"max {ms.max():6.1f} ms")
    print(f"  first 100 median {np.median(ms[:100]):6.1f} ms   last 100 median {np.median(ms[-100:]):6.1f} ms   "
          f"ratio {np.median(ms[-100:]) / np.median(ms[:100]):.2f}")
    cpu_ms = np.asarray(cpu) * 1e3  # the same in CPU time (what the machine's other processes do not change)
    print(f"  CPU: first 100 median {np.median(cpu_ms[:100]):6.1f} ms   last 100 median {np.median(cpu_ms[-100:]):6.1f} ms"
          f"   ratio {np.median(cpu_ms[-100:]) / np.median(cpu_ms[:100]):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=int, default=300)
    parser.add_argument("--points", type=int, default=10)
    parser.add_argument("--sigma", type=float, default=1.0, help="pixel noise, pixels")
    parser.add_argument("--placements", type=int, default=3, help="placements of mirror 1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch-samples", type=int, default=6, help="image counts at which the batch solve is timed")
    parser.add_argument("--batch-every-image", action="store_true", help="time the batch solve at every image count")
    parser.add_argument("--latency", type=int, nargs="*", metavar="N",
                        help="only the add_image latency p50/p95 over streams of N images (default 1000 10000)")
    parser.add_argument("--rig", type=int, nargs="?", const=20, metavar="K",
                        help="only the general model's stream: a three-camera rig, K shared and K own photographs "
                             "per camera (default 20: 480 images)")
    args = parser.parse_args()
    if args.rig is not None:
        rig_mode(args.rig, args.rig, args.seed)
        return
    if args.latency is not None:
        latency_mode(args.latency or [1000, 10000], args.placements, args.sigma, args.seed)
        return

    ds, _ = simulate_base_case(num_images=args.images, num_points=args.points, pixel_sigma=args.sigma,
                               mirror1_placements=args.placements, seed=args.seed)
    print(f"stream: {len(ds.images)} images, {args.placements} placements of mirror 1 in order, mirror 2 new "
          f"in every image, {args.points} points, {args.sigma} px, seed {args.seed}")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start")

    calibrator = IncrementalCalibrator(ds)
    latency, settled, estimate, first = [], [], None, None
    stream_start = time.perf_counter()
    for n, image in enumerate(ds.images, start=1):
        start = time.perf_counter()
        estimate = calibrator.add_image(image)
        latency.append(time.perf_counter() - start)
        settled.append(calibrator.settled)
        if estimate is not None and first is None:
            first = n
    stream_total = time.perf_counter() - stream_start
    if first is None:
        raise SystemExit("the stream never allowed the analytical solution")
    start = time.perf_counter()
    full = calibrator.calibration(full=True)
    full_time = time.perf_counter() - start

    before = latency[: first - 1]
    after = latency[first:]  # images after the one that started
    after_settled = [t for t, s_before, s in zip(after, settled[first - 1 : -1], settled[first:]) if s_before and s]
    print(f"\nincremental (iSAM2): first estimate at image {first}; start-up there {latency[first - 1]:.2f} s; "
          f"{calibrator.restarts} restart(s) while unsettled; settled at the end: {calibrator.settled}")
    print(f"  buffering before start-up   {stats_ms(before)}")
    print(f"  per image after start-up    {stats_ms(after)}")
    print(f"  ... settled images only     {stats_ms(after_settled)}")
    print(f"  whole stream {stream_total:.2f} s; calibration(full=True) {full_time:.2f} s")

    batch_start = time.perf_counter()
    batch = calibrate(ds)
    batch_final = time.perf_counter() - batch_start
    print(f"\nbatch MLE on all {len(ds.images)} images: {batch_final:.2f} s, {batch.iterations} LM iterations")
    print(f"  last per-image estimate vs batch: max {pose_sigmas(batch, estimate).max():.4f} sigma "
          f"(per axis {np.array2string(pose_sigmas(batch, estimate), precision=4)})")
    print(f"  calibration(full=True) vs batch:  max {pose_sigmas(batch, full).max():.2e} sigma")

    counts = list(range(first, len(ds.images) + 1))
    if args.batch_every_image:
        sampled = counts
    else:
        sampled = sorted({round(c) for c in np.linspace(first, len(ds.images), max(args.batch_samples, 2))})
    times = {}
    for count in sampled:
        if count == len(ds.images):
            times[count] = batch_final
            continue
        prefix = Dataset(ds.num_mirrors, ds.camera, ds.pixel_sigma, ds.fiducials, ds.images[:count], ds.source)
        start = time.perf_counter()
        try:
            calibrate(prefix)
        except Exception as error:  # noqa: BLE001 - a failed solve still took this long
            print(f"  batch on {count} images failed: {type(error).__name__}: {error}")
        times[count] = time.perf_counter() - start
    estimated = float(np.sum(np.interp(counts, sampled, [times[c] for c in sampled])))
    how = "timed at every image count" if args.batch_every_image else (
        f"timed at {len(sampled)} image counts ({', '.join(f'{c}: {times[c]:.1f} s' for c in sampled)}), "
        "linearly interpolated in between")
    print(f"\nbatch re-run after every image from {first} to {len(ds.images)} ({len(counts)} solves): "
          f"{estimated:.0f} s ({how})")
    incremental_after = float(np.sum(latency[first - 1 :]))
    print(f"incremental over the same images: {incremental_after:.1f} s (start-up included) -> "
          f"{estimated / incremental_after:.0f}x less")
    print(f"machine load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
