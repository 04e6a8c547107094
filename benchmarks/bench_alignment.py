"""Live alignment cost: ``Reconstructor.alignment`` + ``spectrum`` against the live heights.

Run from the repository root::

    python3 benchmarks/bench_alignment.py                 # 512^2 and 1024^2
    python3 benchmarks/bench_alignment.py --sizes 1024 --repeats 40 --profile

Frames: the synthetic tank (app/capture/scene.py, ray-traced by
processing/forward.py, 6 px carriers) at still water, the scene every newcomer
sees first, and its travelling waves (the carriers then come from local tiles).
The Reconstructor is the GUI's (default options, FFTW_MEASURE plans).  In one run, taking turns
(4 calls each per round, so all share the machine's load), the median ms of

- ``rec(frame, grid="decimated")``: the live heights (the yardstick);
- ``rec.alignment(frame)`` and ``rec.spectrum(frame)``: the Alignment tab;
- ``app.gui.alignment.frame_alignment(frame)``: the Alignment tab before a
  reference exists (the full carrier search and the spectrum, no heights).

The goal (issue 22) is alignment + spectrum <= 2x the decimated heights at
1024^2.  Before a reference the live worker refreshes the tab every 0.1 s
but gives it at most half its time (app/capture/worker.py), so 10 a second
needs ``frame_alignment`` <= 50 ms.  ``--profile`` adds a cProfile of
alignment + spectrum on still water.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from app.capture.scene import TankScene  # noqa: E402
from app.gui.alignment import frame_alignment  # noqa: E402
from processing.reconstruct import Reconstructor  # noqa: E402


def interleaved_medians(fns, repeats, block=4):
    """Median ms of each fn(); rounds visit every fn in turn, ``block`` calls each."""
    for fn in fns:
        fn()  # warm-up
    times = [[] for _ in fns]
    for _ in range(max(1, repeats // block)):
        for k, fn in enumerate(fns):
            for _ in range(block):
                t = time.perf_counter()
                fn()
                times[k].append(1e3 * (time.perf_counter() - t))
    return [statistics.median(t) for t in times]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv)
    print(f"alignment benchmark, {os.cpu_count()} CPUs visible; median ms, same run (read the ratios)")
    print(f"{'size':>6} {'scene':>6} {'heights':>8} {'alignment':>10} {'spectrum':>9} {'ratio':>6}  goal <= 2x"
          f"   {'before a reference':>18}")
    for n in args.sizes:
        tank = TankScene((n, n), n_frames=2)
        tank.prepare("waves")
        rec = Reconstructor(tank.reference, tank.geometry, planner_effort="FFTW_MEASURE")  # as the GUI
        still = tank(0)
        tank.set_scene("waves")
        waves = tank(1)
        for name, frame in (("still", still), ("waves", waves)):
            theta = tank.geometry.theta_deg
            t = interleaved_medians([lambda: rec(frame, grid="decimated"), lambda: rec.alignment(frame),
                                     lambda: rec.spectrum(frame),
                                     lambda: frame_alignment(frame, theta, geometry=tank.geometry)], args.repeats)
            ratio = (t[1] + t[2]) / t[0]
            print(f"{n:>6} {name:>6} {t[0]:>8.1f} {t[1]:>10.1f} {t[2]:>9.1f} {ratio:>6.2f}x  "
                  f"{'PASS' if ratio <= 2.0 else 'FAIL'}   {t[3]:>9.1f} ms "
                  f"({'10 a second' if t[3] <= 50.0 else f'{500.0 / t[3]:.1f} a second'})")
        if args.profile:
            prof = cProfile.Profile()
            prof.enable()
            for _ in range(5):
                rec.alignment(still)
                rec.spectrum(still)
            prof.disable()
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)


if __name__ == "__main__":
    main()
