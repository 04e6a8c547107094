"""Where the image refinement's time goes, and its cost against FD's refinement in the same run.

Run from the repository root::

    python3 benchmarks/bench_refine.py                    # 512^2 and 1024^2
    python3 benchmarks/bench_refine.py --sizes 1024 --repeats 6
    python3 benchmarks/bench_refine.py --threads 1 --clock cpu   # one core's CPU time (loaded machine)
    git show 9385a2f:processing/dic.py > /tmp/dic_old.py
    python3 benchmarks/bench_refine.py --threads 1 --clock cpu --against /tmp/dic_old.py

Frames: analytic warps of benchmarks/bench_processing.py's board (speed_frames).
Printed per size, all in one run, variants interleaved so they share the machine's load:

* ms/frame (least of ``--repeats`` rounds of 2 calls: the machine's load only adds)
  of the peer-style yardstick (bench_processing.Baseline: numpy
  FCD, displacement only), the full grid with FD's refinement
  (``refine_method="fd"``) and with the image refinement (``"image"``, every
  caller's full-grid default), and the ratios image / FD and yardstick / image;
* the image refinement's stages (``stage_ms`` of processing.dic.refine_height: ms
  per frame and per Gauss-Newton step); ``--profile`` adds cProfile's top functions;
* with ``--against FILE``: ``refine_height`` of another version of processing/dic.py
  and of this one on the same inputs, interleaved, and how far their answers differ.
"""

from __future__ import annotations

import argparse
import cProfile
import math
import os
import pstats
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from benchmarks.bench_processing import GEOMETRY, Baseline, speed_frames  # noqa: E402
from processing import dic  # noqa: E402
from processing.reconstruct import Reconstructor  # noqa: E402

CLOCK = time.perf_counter


def interleaved_least(fns, rounds, block=2):
    """Least ms per call of each of ``fns`` (called with a counter), in ``rounds``
    rounds of ``block`` calls each, variants in turn (one warm-up call each): on a
    loaded machine the least is what the code costs, the median what the neighbours do."""
    for fn in fns:
        fn(0)
    best = [math.inf] * len(fns)
    i = 0
    for _ in range(rounds):
        for j, fn in enumerate(fns):
            for _ in range(block):
                t = CLOCK()
                fn(i)
                best[j] = min(best[j], CLOCK() - t)
                i += 1
    return [1e3 * b for b in best]


def stage_times(rec, frame, calls=5):
    """ms of each stage of the image refinement in ``rec(frame)`` (the
    ``stage_ms`` of :func:`processing.dic.refine_height`, which the benchmark
    hands it by wrapping the module's function), and of the whole call: the
    least of ``calls`` calls each (the machine's load only adds time)."""
    best = {}
    inner = dic.refine_height
    stages = {}

    def timed(*a, **kw):
        return inner(*a, stage_ms=stages, **kw)

    dic.refine_height = timed
    try:
        total = math.inf
        for _ in range(calls):
            stages.clear()
            rec.reset_series()
            t = CLOCK()
            rec(frame, grid="full")
            total = min(total, CLOCK() - t)
            for k, v in stages.items():
                best[k] = min(best.get(k, math.inf), v)
    finally:
        dic.refine_height = inner
    return best, 1e3 * total


def profile(rec, frame, top=18):
    """cProfile of one call: the functions with the most own time."""
    prof = cProfile.Profile()
    rec.reset_series()
    prof.enable()
    rec(frame, grid="full")
    prof.disable()
    pstats.Stats(prof).sort_stats("tottime").print_stats(top)


def against(path, rec, ref, frame, rounds):
    """``refine_height`` of the processing/dic.py at ``path`` (another version,
    e.g. ``git show 9385a2f:processing/dic.py > /tmp/dic_old.py``) and of this
    one on the same inputs (what ``rec(frame)`` hands it), interleaved: least ms
    each (CLOCK) and the largest difference of their displacements."""
    import importlib.util

    import numpy as np

    spec = importlib.util.spec_from_file_location("dic_other", path)
    other = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(other)
    cap = {}
    inner = dic.refine_height

    def grab(*a, **kw):
        cap["a"], cap["kw"] = a, kw
        return inner(*a, **kw)

    dic.refine_height = grab
    try:
        rec.reset_series()
        rec(frame, grid="full")
    finally:
        dic.refine_height = inner
    a, kw = cap["a"], cap["kw"]
    kw_other = {k: v for k, v in kw.items() if k in ("outer", "period_px", "intensity_cell_px")}
    a_other = a[:4] + (other.HeightNodes(GEOMETRY, other.NodeGrid(ref.shape)),)
    best = [math.inf, math.inf]
    for _ in range(rounds):
        for j in range(2):
            t = CLOCK()
            if j == 0:
                _, u_other, _ = other.refine_height(*a_other, **kw_other)
            else:
                _, u_this, _ = dic.refine_height(*a, **kw)
            best[j] = min(best[j], CLOCK() - t)
    return 1e3 * best[0], 1e3 * best[1], float(np.abs(u_this - u_other).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2, help="the Reconstructor's threads option")
    ap.add_argument("--profile", action="store_true", help="also print cProfile's top functions")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="cpu: the process's CPU time (all its threads), for a machine others load; "
                         "with --threads 1 it is what one core of a --workers run spends")
    ap.add_argument("--against", metavar="DIC_PY",
                    help="also time refine_height of this other version of processing/dic.py on the same inputs")
    args = ap.parse_args(argv)
    global CLOCK
    if args.clock == "cpu":
        CLOCK = time.process_time
    import cv2

    cv2.setNumThreads(args.threads)  # what app/batch/parallel.py gives a worker
    for n in args.sizes:
        ref, frames = speed_frames(n)
        nf = len(frames)
        opts = dict(planner_effort="FFTW_MEASURE", threads=args.threads)
        rec_fd = Reconstructor(ref, GEOMETRY, grid="full", refine_method="fd", **opts)
        rec_img = Reconstructor(ref, GEOMETRY, grid="full", refine_method="image", carriers=rec_fd.carriers, **opts)
        base = Baseline(ref, rec_fd.carriers)

        def single(rec):
            def call(i):
                rec.reset_series()
                return rec(frames[i % nf], grid="full")
            return call

        t = interleaved_least([lambda i: base(frames[i % nf]), single(rec_fd), single(rec_img)], args.repeats)
        print(f"{n}^2 (threads={args.threads}, {args.clock} clock): yardstick {t[0]:.1f} ms, "
              f"full FD refinement {t[1]:.1f} ms, "
              f"full image refinement {t[2]:.1f} ms; image/FD {t[2] / t[1]:.2f}x (goal <= 2.5x), "
              f"yardstick/image {t[0] / t[2]:.2f}x (goal >= 3x)")
        stages, total = stage_times(rec_img, frames[1])
        steps = rec_img.image_iterations
        print(f"  image refinement stages (least ms of 5 frames; whole call {total:.1f} ms, refine_height "
              f"{sum(stages.values()):.1f} ms, at most {steps} Gauss-Newton steps):")
        for k, v in sorted(stages.items(), key=lambda kv: -kv[1]):
            print(f"    {k:<12} {v:8.1f}   ({v / steps:6.1f} per step)")
        if args.against:
            t_other, t_this, du = against(args.against, rec_img, ref, frames[1], max(args.repeats, 4))
            print(f"  refine_height: {args.against} {t_other:.1f} ms, this {t_this:.1f} ms "
                  f"({t_this / t_other:.3f}x); displacements differ by at most {du:.2g} px")
        if args.profile:
            profile(rec_img, frames[1])


if __name__ == "__main__":
    main()
