"""Processing speed and accuracy, against a peer-style baseline measured in the same run.

Run from the repository root::

    python3 benchmarks/bench_processing.py              # speed at 512^2, 1024^2, 2048^2 + accuracy
    python3 benchmarks/bench_processing.py --sizes 1024 --repeats 30
    python3 benchmarks/bench_processing.py --no-accuracy
    python3 benchmarks/bench_processing.py --no-accuracy --sizes   # issue 22's table alone
    python3 benchmarks/bench_processing.py --no-speed --no-issue22 --no-accuracy --masked 4   # beside a blank patch

Speed: median milliseconds per frame, FFTW plans (FFTW_MEASURE) built outside
the timed loop, one warm-up call; all variants, baseline included, are timed
in rounds of 4 calls each so that they share the (possibly shared) machine's
load.  The baseline is what peers do: numpy FFT in
float64, one full-size fft2 of the frame, two full-size masked ifft2 (one per
carrier), phase of the product with the conjugate reference and the 2 x 2
solve for the displacement; no unwrapping, no mask, no height.  Goals:
reference-to-height on the decimated grid >= 15x faster than the baseline's
displacement alone, full pixel grid >= 5x.

Frames for speed are analytic warps ``I0(r - u(r))`` of a soft checkerboard
(ray tracing 2048^2 frames would take minutes) with a dimple-like
displacement whose carrier phase reaches about 5 rad, so the unwrapper runs.

Accuracy: ray-traced TIR frames (processing.forward), relative RMS height
error in the interior after removing the null space, for the default
settings, the options, and the published method.  Each pixel is rendered
from ``--supersample`` x ``--supersample`` rays (default
:data:`ACCURACY_SUPERSAMPLE`); the last line says whether any refinement
came out worse than none on any case (issue 19).

The table renders each case with one placement of the board on the pixels.
At the accuracy these methods reach (0.03-0.3 %), the board's phase against
the pixel grid moves every column's figure by more than the columns differ
(the deep dimple without refinement 0.05-0.16 % over board placements, the
2 um bump 0.10-0.47 %): ``--placements K`` then renders every case K times,
the board shifted by seeded random offsets within one period (the first
placement is the table's), and compares each refinement with no refinement
on the same frames (paired differences): a refinement is called worse where
its mean excess is more than twice its standard error and more than
:data:`WORSE_BY_POINTS` (about a minute per 4 placements).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from processing.geometry import Geometry  # noqa: E402
from processing.reconstruct import Reconstructor  # noqa: E402

GEOMETRY = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)


# ---------------------------------------------------------------- frames
def board(shape, period_px=20.0, aspect=math.cos(math.radians(55))):
    r, c = np.mgrid[: shape[0], : shape[1]].astype(np.float32)
    k = 2 * np.pi / period_px
    return r, c, lambda rr, cc: (0.5 + 0.4 * np.tanh(3 * np.sin(k * cc) * np.sin(k * rr / aspect)))


def speed_frames(n, count=6):
    """Reference and ``count`` frames of a dimple growing from 85 % to 100 %
    (a live series: consecutive frames differ a little)."""
    r, c, pat = board((n, n))
    ref = (pat(r, c) * 255).astype(np.uint8)
    s = 0.12 * n
    g = np.exp(-((r - 0.45 * n) ** 2 + (c - 0.55 * n) ** 2) / (2 * s * s))
    frames = []
    for a in np.linspace(0.85, 1.0, count):
        u_r = a * 8.0 * g  # px: about 5 rad on the row-dominated carrier
        u_c = a * 3.0 * g
        frames.append((pat(r - u_r, c - u_c) * 255).astype(np.uint8))
    return ref, frames


# --------------------------------------------------------------- baseline
class Baseline:
    """Peer-style FD: numpy float64, full-size masks, two full-size inverse FFTs."""

    def __init__(self, reference, carriers):
        ref = np.asarray(reference, np.float64)
        rows, cols = ref.shape
        self.shape = ref.shape
        fr = np.fft.fftfreq(rows)[:, None]
        fc = np.fft.fftfreq(cols)[None, :]
        self.masks = []
        kb = np.round(carriers.freq * np.array([rows, cols])) / np.array([rows, cols])
        radius = 0.5 * carriers.min_spacing
        for s in range(2):
            self.masks.append(np.hypot(fr - kb[s, 0], fc - kb[s, 1]) < radius)
        self.K = 2 * np.pi * kb
        spec = np.fft.fft2(ref)
        self.g0c = [np.conj(np.fft.ifft2(spec * m)) for m in self.masks]

    def __call__(self, frame):
        spec = np.fft.fft2(np.asarray(frame, np.float64))
        phases = [np.angle(np.fft.ifft2(spec * m) * g0c) for m, g0c in zip(self.masks, self.g0c)]
        inv = -np.linalg.inv(self.K)
        u_r = inv[0, 0] * phases[0] + inv[0, 1] * phases[1]
        u_c = inv[1, 0] * phases[0] + inv[1, 1] * phases[1]
        return u_r, u_c


def rel_height_error(res, surface, geometry=GEOMETRY, margin=0.08):
    """Relative RMS height error (%) of ``res`` against the ray-traced ``surface``:
    interior (``margin`` of each side left out), valid samples, null space
    ``a exp(-T y / H)`` removed from both."""
    from processing import forward as F

    n_rows, n_cols = res.carriers.shape
    truth = F.true_height(surface, geometry, (n_rows, n_cols), rows_px=res.rows_px, cols_px=res.cols_px)
    R, C = np.meshgrid(res.rows_px, res.cols_px, indexing="ij")
    inner = res.valid & (R > margin * n_rows) & (R < (1 - margin) * n_rows)
    inner &= (C > margin * n_cols) & (C < (1 - margin) * n_cols)
    _, y = geometry.to_canonical_xy(res.x_mm, res.y_mm)
    null = np.broadcast_to(np.exp(-geometry.T * np.asarray(y)[:, None] / geometry.depth_mm), truth.shape)[inner]
    d = (res.height - truth)[inner]
    t = truth[inner]
    d = d - null * (null @ d) / (null @ null)
    t = t - null * (null @ t) / (null @ null)
    return 100 * float(np.sqrt(np.mean(d**2)) / np.sqrt(np.mean(t**2)))


def heldout_frames(n, count=3):
    """Ray-traced reference and ``count`` frames of a random wave field (1 um rms,
    12-30 mm) at ``n``^2, 12 bit, and the surfaces (a held-out case: no setting
    of the refinement was tuned on it)."""
    from processing import forward as F

    board_ = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    rng = np.random.default_rng(0)
    ref, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (n, n), board_, supersample=2)
    surfaces = [F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=10 + k)
                for k in range(count)]
    frames = [F.quantize(F.render_tir(sf, GEOMETRY, (n, n), board_, supersample=2)[0], bits=12, rng=rng)
              for sf in surfaces]
    return F.quantize(ref, bits=12, rng=rng), frames, surfaces


def blank_patch(frame):
    """``frame`` with :data:`BLANK_PATCH` (given for 256^2) scaled to its size set to its mean grey."""
    out = np.array(frame, copy=True)
    rows, cols = out.shape
    r, c = BLANK_PATCH
    out[r.start * rows // 256:r.stop * rows // 256, c.start * cols // 256:c.stop * cols // 256] = int(out.mean())
    return out


def bench_issue22(n, repeats, thread_counts):
    """Issue 22's table: each path's ms/frame on a ray-traced ``n``^2 frame, its
    speed against the peer-style yardstick (Baseline: numpy FCD, displacement
    only, no height) measured in the same rounds, and its height error, at
    each of ``thread_counts`` (the Reconstructor's ``threads`` and OpenCV's);
    last, the default on the same frames with :data:`BLANK_PATCH` (scaled to
    ``n``) blanked: what masked samples cost, which the all-valid frames do
    not show."""
    ref, frames, surfaces = heldout_frames(n)
    nf = len(frames)
    print(f"Issue 22 table: {n}^2 ray-traced frames (random waves 1 um rms, 12-30 mm, 12 bit), "
          f"median ms/frame of interleaved rounds; height error: rel. RMS %, mean of {nf} frames")
    for threads in thread_counts:
        cv2.setNumThreads(threads)
        opts = dict(planner_effort="FFTW_MEASURE", threads=threads)
        rec_live = Reconstructor(ref, GEOMETRY, grid="decimated", **opts)
        carriers = rec_live.carriers
        paths = [("live decimated (FD)", rec_live, "decimated"),
                 ("full grid, no refinement", Reconstructor(ref, GEOMETRY, grid="full", refine_iterations=0,
                                                            carriers=carriers, **opts), "full"),
                 ("full grid, FD refinement", Reconstructor(ref, GEOMETRY, grid="full", refine_method="fd",
                                                            carriers=carriers, **opts), "full"),
                 ("full grid, image refinement (default)", Reconstructor(ref, GEOMETRY, carriers=carriers, **opts),
                  "full")]
        base = Baseline(ref, carriers)

        def call(rec, grid):
            def run(i):
                rec.reset_series()
                return rec(frames[i % nf], grid=grid)
            return run

        # the default again on the same frames with a blank patch (lost contrast: a shadow, a splash):
        # what a frame with masked samples costs, which the all-valid frames above do not show
        blanked = [blank_patch(f) for f in frames]
        rec_default = paths[-1][1]

        def call_blanked(i):
            rec_default.reset_series()
            return rec_default(blanked[i % nf])

        fns = [lambda i: base(frames[i % nf])] + [call(rec, grid) for _, rec, grid in paths] + [call_blanked]
        t = interleaved_medians(fns, repeats, block=2)
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        print(f"  threads {threads} (load average {load:.1f})")
        print(f"  {'path':40s} {'ms/frame':>9s} {'x yardstick':>12s} {'x FD ref.':>10s} {'height error':>13s}")
        print(f"  {'yardstick (displacement only)':40s} {t[0]:9.1f} {1.0:11.1f}x {'':>10s} {'-':>13s}")
        for (label, rec, grid), ms in zip(paths, t[1:]):
            err = "-"
            if grid == "full":
                errs = []
                for frame, sf in zip(frames, surfaces):
                    rec.reset_series()
                    errs.append(rel_height_error(rec(frame, grid=grid), sf))
                err = f"{np.mean(errs):.3f} %"
            print(f"  {label:40s} {ms:9.1f} {t[0] / ms:11.1f}x {ms / t[3]:9.2f}x {err:>13s}")
        errs = []
        for frame, sf in zip(blanked, surfaces):
            rec_default.reset_series()
            errs.append(rel_height_error(rec_default(frame), sf))
        print(f"  {'  the default beside a blank patch':40s} {t[-1]:9.1f} {t[0] / t[-1]:11.1f}x "
              f"{t[-1] / t[3]:9.2f}x {np.mean(errs):11.3f} %")
    print("  goals (issue 22): default >= 3x the yardstick and <= 2.5x FD refinement's time; issue 19: "
          "live decimated >= 25x, default within 5x of FD's batch time")
    print()


def interleaved_medians(fns, repeats, every=None, block=4, warm_ms=40.0):
    """Median ms of each fn(i).  Rounds visit every fn in turn, ``block``
    calls at a time, so that all see the same machine load (the machine may
    be shared) while each runs in its steady state, as in a live loop or a
    batch, where one chain runs frame after frame: each block begins with
    untimed calls (other frames) for at least ``warm_ms``, which take the
    caches and memory back from the fn before it.  Timing from the first
    call made a small, fast fn pay for a big one's traffic: the live 1024^2
    chain, one thread, after the default (7 Dec 2026): 3.6, 3.2, 3.0, 3.0,
    2.8, 2.8, 2.8, 2.8 ms for the 1st to 8th call after one untimed call,
    2.7 ms on its own; the issue-22 table said 6.6 ms timing every call.
    ``every[k]`` > 1 visits fn k only every that-many rounds."""
    every = every or [1] * len(fns)
    for fn in fns:
        fn(0)  # warm-up
    times = [[] for _ in fns]
    rounds = max(1, repeats // block)
    for r in range(rounds):
        for k, fn in enumerate(fns):
            if r % every[k]:
                continue
            t_warm, w = time.perf_counter() + warm_ms / 1e3, 0
            while True:  # untimed: frames after the block's (other ones, as in a series)
                w += 1
                fn(r * block + block + w)
                if time.perf_counter() >= t_warm:
                    break
            for j in range(block):
                i = r * block + j
                t = time.perf_counter()
                fn(i)
                times[k].append(1e3 * (time.perf_counter() - t))
    return [statistics.median(t) for t in times]


def bench_speed(sizes, repeats):
    print("Speed (median ms/frame, 2 FFTW threads, FFTW_MEASURE planned before timing;")
    print("variants timed in turn, 4 calls each per round, so they share the machine's load)")
    print("  dec series / full live: consecutive frames of a live series (temporal unwrapping),")
    print("    no refinement; dec single: spatial unwrapping from scratch every frame;")
    print("  full batch: FD on the full grid (refine_method='fd', 1 refinement iteration),")
    print("    spatial unwrapping every frame; full ifft: full-size inverse FFTs + full-grid solve")
    print(f"{'size':>6} {'baseline':>9} {'dec series':>11} {'x':>6} {'dec single':>11} {'x':>6} "
          f"{'full live':>10} {'x':>6} {'full batch':>11} {'x':>6} {'full ifft':>10} {'x':>5}  grid     verdict")
    for n in sizes:
        ref, frames = speed_frames(n)
        nf = len(frames)
        opts = dict(planner_effort="FFTW_MEASURE")
        rec_dec = Reconstructor(ref, GEOMETRY, grid="decimated", **opts)
        carriers = rec_dec.carriers
        rec_full = Reconstructor(ref, GEOMETRY, grid="full", refine_iterations=0, carriers=carriers, **opts)
        rec_single = Reconstructor(ref, GEOMETRY, carriers=carriers, **opts)
        rec_batch = Reconstructor(ref, GEOMETRY, grid="full", refine_method="fd", carriers=carriers, **opts)
        rec_ifft = Reconstructor(ref, GEOMETRY, grid="full", full_method="ifft", carriers=carriers, **opts)
        rec_image = Reconstructor(ref, GEOMETRY, grid="full", refine_method="image", carriers=carriers, **opts)
        base = Baseline(ref, carriers)

        def series(rec):
            return lambda i: rec(frames[i % nf])

        def single(rec, grid):
            def call(i):
                rec.reset_series()
                return rec(frames[i % nf], grid=grid)
            return call

        fns = [lambda i: base(frames[i % nf]), series(rec_dec), single(rec_single, "decimated"),
               series(rec_full), single(rec_batch, "full"), single(rec_ifft, "full"), single(rec_image, "full")]
        slow = 3 if n >= 2048 else 1
        t = interleaved_medians(fns, repeats, every=[slow, 1, 1, 1, 1, 2 * slow, slow])
        t_base = t[0]
        ratios = [t_base / x for x in t[1:]]
        verdict = ("PASS" if ratios[0] >= 15 else "FAIL") + " dec>=15x, " + \
                  ("PASS" if ratios[2] >= 5 else "FAIL") + " full>=5x (live)" + \
                  (", batch " + ("PASS" if ratios[3] >= 5 else "FAIL"))
        m = rec_dec.demod.window_shape
        print(f"{n:>6} {t_base:>9.1f} {t[1]:>11.2f} {ratios[0]:>6.1f} {t[2]:>11.2f} {ratios[1]:>6.1f} "
              f"{t[3]:>10.2f} {ratios[2]:>6.1f} {t[4]:>11.2f} {ratios[3]:>6.1f} "
              f"{t[5]:>10.1f} {ratios[4]:>5.1f}  {m[0]}x{m[1]}  {verdict}")
        print(f"{'':>6} full image (refine_method='image', every caller's full-grid default): {t[6]:.1f} ms/frame, "
              f"{t[6] / t[4]:.1f}x full batch with FD's refinement ({t[4]:.1f} ms); goal <= 5x")
        for label, rec in (("full live", rec_full), ("full batch", rec_batch), ("full image", rec_image)):
            res = rec(frames[1])
            stages = ", ".join(f"{k} {v:.1f}" for k, v in res.timings_ms.items())
            print(f"{'':>6} stages of one {label} call (ms): {stages}")
    print()


# --------------------------------------------------------------- accuracy
#: Rays per pixel side of the accuracy table's renders (8 x 8 a pixel).  The
#: board's 0.1 mm edges are 1 px wide: with 2 x 2 rays (the table until
#: 2026-12-03) the render aliases them, and under perspective (camera at
#: 1.5 m) the aliasing differs across the field: moire bands in u_row that
#: every method measured alike, 0.42-0.48 % on the camera's bump, which
#: made image matching look worse than no refinement (0.48 vs 0.42 %).  With
#: 4 x 4 rays 0.09 / 0.07 / 0.08 % (none / FD / image), 6 x 6 and 8 x 8 within
#: 0.01 points of each other (0.13 / 0.08 / 0.08 %).  Telecentric cases moved
#: by up to 0.16 points (board sharp 0.1 mm: 0.31 -> 0.15 %, image matching).
#: About 100 s for the table instead of 20 s.
ACCURACY_SUPERSAMPLE = 8


#: Each refined column of the accuracy table and the unrefined one it must not be worse than.
REFINED_AGAINST_NONE = (("full fd", "full no-ref"), ("full image", "full no-ref"), ("default", "full no-ref"),
                        ("dec refine 1", "decimated"))


def refinement_verdict(rows, pairs=REFINED_AGAINST_NONE):
    """Issue 19: where a refinement came out worse than none, as
    ``"case: column a.aa > column b.bb"`` strings (``rows``: ``(case, {column:
    error %})``; compared as printed, to 0.01 points)."""
    worse = []
    for case, cells in rows:
        for refined, plain in pairs:
            if refined in cells and plain in cells and round(cells[refined], 2) > round(cells[plain], 2):
                worse.append(f"{case}: {refined} {cells[refined]:.2f} > {plain} {cells[plain]:.2f}")
    return worse


#: A refinement is worse than none over board placements (``--placements``) only by more than this
#: (points of rel. RMS height error, besides twice the paired difference's standard error).
WORSE_BY_POINTS = 0.01


def placement_offsets(k: int, period_mm: float = 2.0):
    """``k`` board offsets (x, y) mm: the table's (0, 0), then seeded uniform ones within one period."""
    extra = np.random.default_rng(7).uniform(0.0, period_mm, (max(0, k - 1), 2))
    return [(0.0, 0.0)] + [(float(x), float(y)) for x, y in extra]


def paired_verdict(errors, pairs=REFINED_AGAINST_NONE, min_points=WORSE_BY_POINTS):
    """``(lines, worse)`` of one case over board placements: ``errors`` maps a column to its error (%) at
    each placement (the same frames for every column); for each (refined, plain) pair the paired
    difference's mean and standard error, and whether the refinement is worse (mean > 2 SE and >
    ``min_points``)."""
    lines, worse = [], []
    for refined, plain in pairs:
        if refined not in errors or plain not in errors:
            continue
        d = np.asarray(errors[refined]) - np.asarray(errors[plain])
        se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else float("nan")
        bad = bool(d.mean() > min_points and d.mean() > 2.0 * se)
        lines.append(f"{refined} - {plain} {d.mean():+.3f} (se {se:.3f}){' WORSE' if bad else ''}")
        if bad:
            worse.append(f"{refined} {np.mean(errors[refined]):.3f} > {plain} {np.mean(errors[plain]):.3f}")
    return lines, worse


def accuracy_cases():
    """``[(label, surface, render options), ...]``: the accuracy table's checkerboard cases."""
    from processing import forward as F

    return [
        ("bump 4 um, sigma 5 mm", F.GaussianBump(0.004, 5.0), {}),
        ("bump 2 um, sigma 4 mm", F.GaussianBump(0.002, 4.0), {}),
        ("bump 2 um, sigma 2.5 mm (narrow)", F.GaussianBump(0.002, 2.5), {}),
        ("waves 1 um rms, 12-30 mm", F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=3), {}),
        ("dimple 5 um, 12 bit, noise 20 DN", F.Dimple(0.005, 6.0), dict(bits=12, noise=20.0)),
        ("deep dimple 15 um, sigma 9 mm", F.Dimple(0.015, 9.0), {}),
        ("board soft 0.4 mm, period 2.1 mm, bump", F.GaussianBump(0.004, 5.0),
         dict(pattern=F.Checkerboard(period_mm=2.1, edge_softness_mm=0.4))),
        ("board sharp 0.1 mm, period 2.1 mm, bump", F.GaussianBump(0.004, 5.0),
         dict(pattern=F.Checkerboard(period_mm=2.1, edge_softness_mm=0.1))),
        # issue 11: features 3-6 carrier periods long (2 mm board), 12 bit
        ("waves 0.3 um rms, 6-12 mm, 12 bit", F.WaveField.random(8, amplitude_rms_mm=0.0003,
                                                                 wavelength_range_mm=(6, 12), seed=1), dict(bits=12)),
        ("bump 1 um, sigma 3 mm (1.5 periods), 12 bit", F.GaussianBump(0.001, 3.0), dict(bits=12)),
    ]


def render_case(surface, supersample, geometry=GEOMETRY, n=256, bits=8, noise=0.0, pattern=None, offset=(0.0, 0.0)):
    """``(reference, frame)`` of an accuracy case: flat water and ``surface`` ray-traced at ``n``^2 with
    ``supersample``^2 rays a pixel through ``pattern`` (None: the 2 mm board) shifted by ``offset`` mm,
    quantised to ``bits`` with ``noise`` DN rms (the same seeded noise for every case)."""
    from processing import forward as F

    pattern = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1) if pattern is None else pattern
    rng = np.random.default_rng(0)
    ref, _ = F.render_tir(F.FlatSurface(), geometry, (n, n), pattern, supersample=supersample,
                          pattern_offset_mm=offset)
    img, _ = F.render_tir(surface, geometry, (n, n), pattern, supersample=supersample, pattern_offset_mm=offset)
    return (F.quantize(ref, bits=bits, noise_rms=noise, rng=rng),
            F.quantize(img, bits=bits, noise_rms=noise, rng=rng))


def bench_accuracy(supersample=ACCURACY_SUPERSAMPLE, placements=1):
    from processing import forward as F

    def render(surface, **kw):
        return render_case(surface, supersample, **kw)

    rel = rel_height_error

    cases = accuracy_cases()
    variants = [
        ("decimated", dict(grid="decimated")),
        ("full fd", dict(grid="full", refine_method="fd")),
        ("full no-ref", dict(grid="full", refine_iterations=0)),
        ("full ifft", dict(grid="full", full_method="ifft")),
        ("full cubic", dict(grid="full", full_interpolation="cubic", refine_method="fd")),
        ("dec disc", dict(grid="decimated", filter_shape="disc")),
        ("dec no-apod", dict(grid="decimated", border="none")),
        ("dec refine 1", dict(grid="decimated", refine_iterations=1)),
        ("full image", dict(grid="full", refine_method="image")),
        ("default", {}),  # the README's snippet: Reconstructor(reference, geometry)(frame)
        ("published", dict(grid="full", filter_shape="disc", filter_radius=0.5, subbin=False,
                           unwrap=False, border="none", refine_iterations=0)),
    ]
    print("Accuracy: rel. RMS height error (%), ray-traced TIR 256^2, H 300 mm, theta 55 deg,")
    print(f"2 mm board (20 x 11.5 px), {supersample} x {supersample} rays a pixel, interior, null space removed")
    print("(full fd: FD's refinement; full image = default: what every caller gets by default)")
    print(f"{'case':42s}" + "".join(f"{name:>13s}" for name, _ in variants))
    table = []
    for label, surface, kw in cases:
        ref, img = render(surface, **kw)
        cells, errors = [], {}
        for name, opts in variants:
            try:
                errors[name] = rel(Reconstructor(ref, GEOMETRY, **opts)(img), surface)
                cells.append(f"{errors[name]:13.2f}")
            except Exception as exc:  # noqa: BLE001 - a failing variant is a result
                cells.append(f"{type(exc).__name__[:12]:>13s}")
        table.append((label, errors))
        print(f"{label:42s}" + "".join(cells))
    # random dots (issue 11): the same surfaces, dots 0.5 mm (5 x 2.9 px), 8 bit, noise 1 DN, PIV with
    # 16 px final windows (a sample every 8 px); goal <= 2 % where features are >= 8 windows (128 px) wide
    dots = F.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=1)

    class _Shape:
        shape = (256, 256)

    print(f"{'random dots, PIV 16 px windows (dec / full: image matching from PIV)':42s}")
    for label, surface, kw in cases:
        if "pattern" in kw:
            continue
        ref, img = render(surface, bits=8, noise=1.0, pattern=dots)
        rec = Reconstructor(ref, GEOMETRY, pattern="dots")
        cells = []
        for grid in ("decimated", "full"):
            try:
                res = dataclasses.replace(rec(img, grid=grid), carriers=_Shape())
                cells.append(f"{rel(res, surface):13.2f}")
            except Exception as exc:  # noqa: BLE001 - a failing variant is a result
                cells.append(f"{type(exc).__name__[:12]:>13s}")
        print(f"{'  ' + label:42s}" + "".join(cells))
    g = Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False, camera_distance_mm=1500.0)
    bump = F.GaussianBump(0.004, 5.0)
    ref, img = render(bump, geometry=g)
    camera = {name: rel(Reconstructor(ref, g, **opts)(img), bump, g) for name, opts in
              (("decimated", dict(grid="decimated")), ("full fd", dict(grid="full", refine_method="fd")),
               ("full no-ref", dict(grid="full", refine_iterations=0)), ("default", {}))}
    table.append(("camera at 1.5 m, theta 60, bump", camera))
    print(f"{'camera 1.5 m, theta 60 (dec/fd/none/default)':42s}"
          + "".join(f"{v:13.2f}" for v in camera.values()))
    worse = refinement_verdict(table)
    print("refinement worse than none (full fd / full image / default against full no-ref, dec refine 1 "
          "against decimated): "
          + ("; ".join(worse) if worse else "on no case"))
    if placements > 1:
        bench_placements(cases, variants, render, placements)
    print()


def bench_placements(cases, variants, render, k):
    """Issue 19's verdict over ``k`` placements of the board (module docstring): per case, the mean error
    of each compared column and the paired differences."""
    compared = {name for pair in REFINED_AGAINST_NONE for name in pair}
    columns = [(name, opts) for name, opts in variants if name in compared]
    offsets = placement_offsets(k)
    print(f"over {k} placements of the board (offsets within one period; the first is the table's): mean "
          f"rel. RMS height error (%), and refinement minus none, paired (worse: mean > 2 SE and > "
          f"{WORSE_BY_POINTS} points)")
    print(f"{'case':42s}" + "".join(f"{name:>13s}" for name, _ in columns))
    all_worse = []
    for label, surface, kw in cases:
        errors = {name: [] for name, _ in columns}
        for offset in offsets:
            ref, img = render(surface, offset=offset, **kw)
            for name, opts in columns:
                errors[name].append(rel_height_error(Reconstructor(ref, GEOMETRY, **opts)(img), surface))
        lines, worse = paired_verdict(errors)
        all_worse += [f"{label}: {w}" for w in worse]
        print(f"{label:42s}" + "".join(f"{np.mean(errors[name]):13.3f}" for name, _ in columns))
        print(f"{'':44s}" + "; ".join(lines))
    print(f"refinement worse than none over {k} placements: " + ("; ".join(all_worse) if all_worse else "on no case"))


#: The blank patch of :func:`bench_masked` (rows, columns of a 256^2 frame): lost contrast, as under a
#: shadow, a splash or a corner out of the light.
BLANK_PATCH = np.s_[150:190, 40:110]


def bench_masked(placements, supersample=4):
    """The table's checkerboard cases with :data:`BLANK_PATCH` blanked in the frame (its mean grey), over
    ``placements`` board placements: mean error of no refinement, FD's and the default, and the paired
    verdict (a refinement worse than none beside masked pixels: issue 19's "refinement never hurts")."""
    columns = [("full no-ref", dict(refine_iterations=0)), ("full fd", dict(refine_method="fd")), ("default", {})]
    print(f"Beside a blank patch (rows 150-190, columns 40-110 of 256^2; {supersample} x {supersample} rays, "
          f"{placements} placements): mean rel. RMS height error (%)")
    print(f"{'case':42s}" + "".join(f"{name:>13s}" for name, _ in columns) + f"{'valid':>8s}")
    all_worse = []
    for label, surface, kw in accuracy_cases():
        if "pattern" in kw:
            continue
        errors, valid = {name: [] for name, _ in columns}, []
        for offset in placement_offsets(placements):
            ref, img = render_case(surface, supersample, offset=offset, **kw)
            img = blank_patch(img)
            for name, opts in columns:
                res = Reconstructor(ref, GEOMETRY, **opts)(img)
                errors[name].append(rel_height_error(res, surface))
                valid.append(res.valid.mean())
        lines, worse = paired_verdict(errors)
        all_worse += [f"{label}: {w}" for w in worse]
        print(f"{label:42s}" + "".join(f"{np.mean(errors[name]):13.3f}" for name, _ in columns)
              + f"{np.mean(valid):8.3f}")
        print(f"{'':44s}" + "; ".join(lines))
    print("refinement worse than none beside the patch: " + ("; ".join(all_worse) if all_worse else "on no case"))
    print()


def bench_dots_speed(sizes, repeats):
    """Cost per frame of random-dot frames (PIV) against the checkerboard batch
    default, interleaved in the same run (analytic warps, as for the speed table)."""
    print("Random dots (PIV, 16 px final windows) vs checkerboard batch default, median ms/frame")
    for n in sizes:
        rng = np.random.default_rng(1)
        ref_board, frames_board = speed_frames(n, count=3)
        r, c = np.mgrid[:n, :n].astype(np.float32)
        dots = np.zeros((n, n), np.float32)
        k = int(0.3 * n * n / 25)
        dots[rng.integers(0, n, k), rng.integers(0, n, k)] = 1.0
        dots = cv2.GaussianBlur(dots, (0, 0), 1.0)
        dots = dots / dots.max()
        s = 0.12 * n
        g = np.exp(-((r - 0.45 * n) ** 2 + (c - 0.55 * n) ** 2) / (2 * s * s))
        frames_dots = [(cv2.remap(dots, c - a * 3.0 * g, r - a * 8.0 * g, cv2.INTER_CUBIC) * 255).clip(0, 255)
                       .astype(np.uint8) for a in (0.9, 1.0)]
        ref_dots = (dots * 255).astype(np.uint8)
        rb = Reconstructor(ref_board, GEOMETRY, planner_effort="FFTW_MEASURE")
        rd = Reconstructor(ref_dots, GEOMETRY, pattern="dots")
        t = interleaved_medians([lambda i: (rb.reset_series(), rb(frames_board[i % 3])),
                                 lambda i: rd(frames_dots[i % 2])], max(4, repeats // 4))
        print(f"{n:>6} checkerboard batch {t[0]:8.1f}   dots {t[1]:8.1f}   ratio {t[1] / t[0]:5.1f}x")
        bench_piv_passes(ref_dots, frames_dots, max(4, repeats // 4))
    print()


def bench_piv_passes(reference, frames, repeats):
    """PIV's passes alone (the displacement of the dots' decimated grid, the
    live view's): OpenPIV's own loop (``openpiv.windef``, SciPy backend: what
    ran before 2026-12-03) against processing/piv.py's passes with OpenPIV's
    own stages correlating on each of its backends (the same vectors bit for
    bit) and with the compiled stages (``"fftw"``, the default: correlation on
    FFTW plans, validation and replacement compiled; within 1e-6 px), every
    core of the machine."""
    from processing.piv import DotDisplacement, correlation_backend
    from tests.processing.test_piv import openpiv_windef_passes

    threads = os.cpu_count() or 1
    own = {b: DotDisplacement(reference, threads=threads, backend=b)
           for b in dict.fromkeys(("scipy", correlation_backend(), "fftw"))}
    img = [np.asarray(f, np.float64) for f in frames]
    fns = [lambda i: openpiv_windef_passes(own["scipy"], reference, img[i % 2], "scipy")]
    fns += [lambda i, p=p: p.passes(img[i % 2]) for p in own.values()]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = interleaved_medians(fns, repeats)
    line = "  ".join(f"own passes ({b}) {ms:7.1f} ({t[0] / ms:.1f}x)" for b, ms in zip(own, t[1:]))
    print(f"{'':>6} PIV passes: openpiv.windef loop (scipy) {t[0]:7.1f}   {line}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[512, 1024, 2048])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--no-issue22", action="store_true", help="leave out issue 22's table (ray-traced 1024^2)")
    ap.add_argument("--issue22-size", type=int, default=1024)
    ap.add_argument("--placements", type=int, default=8,
                    help="board placements of issue 19's paired verdict (1: the table alone; default 8)")
    ap.add_argument("--masked", type=int, default=0, metavar="K",
                    help="the table's cases beside a blank patch over K placements (issue 19; 0: not run)")
    ap.add_argument("--supersample", type=int, default=ACCURACY_SUPERSAMPLE,
                    help=f"rays per pixel side of the accuracy table's renders (default {ACCURACY_SUPERSAMPLE})")
    args = ap.parse_args(argv)
    cv2.setNumThreads(2)
    print(f"tirdeflect processing benchmark, {os.cpu_count()} CPUs visible, numpy {np.__version__}\n")
    if not args.no_speed and not args.no_issue22:
        bench_issue22(args.issue22_size, max(4, args.repeats // 2), sorted({1, os.cpu_count() or 1}))
        cv2.setNumThreads(2)
    if not args.no_speed and args.sizes:
        bench_speed(args.sizes, args.repeats)
        bench_dots_speed([n for n in args.sizes if n <= 1024], args.repeats)
    if not args.no_accuracy:
        bench_accuracy(args.supersample, args.placements)
    if args.masked:
        bench_masked(args.masked)


if __name__ == "__main__":
    main()
