"""Where a `device="cuda"` batch spends its time: each stage of processing.gpu.BatchChain
timed with the device synchronised around it (so the stages add up to the batch).

    python3 benchmarks/gpu_profile.py [--size 1024] [--batch 32] [--rounds 5]

Needs CuPy and a GPU (or NumPy named cupy, tests/processing/numpy_cupy, for a dry run).
Prints, per grid, milliseconds per frame of each stage, medians over the rounds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

STAGES = ("_demodulate", "_series_start", "_unwrap", "_to_displacement", "_fold_limit", "_refine",
          "_height", "_check_series", "_results")
INNER = ("_decimated", "_warp_smooth", "_up")  # inside the stages above: printed apart, not added


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)
    import cupy

    from gpu_check import _cases
    from processing import Geometry, Reconstructor
    from processing import gpu as G

    spent = defaultdict(list)

    def timed(name, fn):
        def wrapper(self, *a, **k):
            cupy.cuda.Device().synchronize() if hasattr(cupy, "cuda") else None
            t0 = time.perf_counter()
            out = fn(self, *a, **k)
            cupy.cuda.Device().synchronize() if hasattr(cupy, "cuda") else None
            spent[name].append(time.perf_counter() - t0)
            return out
        return wrapper

    for name in STAGES + INNER:
        setattr(G.BatchChain, name, timed(name, getattr(G.BatchChain, name)))
    Reconstructor.validate_frame = timed("validate_frame", Reconstructor.validate_frame)
    INNER_ALL = INNER + ("validate_frame",)
    geometry = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    ref, frames = _cases(args.size, geometry)["travelling waves"]
    order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    stream = [frames[order[k % len(order)]] for k in range(args.batch * (args.rounds + 1))]
    for grid in ("full", "decimated"):
        for essentials in (True, False):
            gpu = Reconstructor(ref, geometry, device="cuda")
            gpu.batch(stream[:args.batch], grid=grid, essentials=essentials)
            spent.clear()
            walls = []
            for k in range(1, args.rounds + 1):
                t0 = time.perf_counter()
                gpu.batch(stream[k * args.batch:(k + 1) * args.batch], grid=grid, essentials=essentials)
                walls.append(time.perf_counter() - t0)
            per = {n: 1e3 * statistics.median(v) / args.batch for n, v in spent.items()}
            wall = 1e3 * statistics.median(walls) / args.batch
            parts = "  ".join(f"{n.strip('_')} {ms:.3f}" for n, ms in per.items() if n not in INNER_ALL)
            parts += "  | inside: " + "  ".join(f"{n.strip('_')} {ms:.3f}" for n, ms in per.items() if n in INNER_ALL)
            stages = sum(ms for n, ms in per.items() if n not in INNER_ALL)
            print(f"{grid:9s} essentials={essentials!s:5s}: {wall:.3f} ms/frame wall "
                  f"(stages {stages:.3f}): {parts}", flush=True)
    # the live window's call: one frame at a time on the decimated grid
    gpu = Reconstructor(ref, geometry, device="cuda", grid="decimated")
    for k in range(10):
        gpu(stream[k % len(stream)])
    spent.clear()
    walls = []
    for k in range(10, 60):
        t0 = time.perf_counter()
        gpu(stream[k % len(stream)])
        walls.append(time.perf_counter() - t0)
    per = {n: 1e3 * statistics.median(v) for n, v in spent.items()}
    parts = "  ".join(f"{n.strip('_')} {ms:.3f}" for n, ms in per.items() if n not in INNER_ALL)
    parts += "  | inside: " + "  ".join(f"{n.strip('_')} {ms:.3f}" for n, ms in per.items() if n in INNER_ALL)
    stages = sum(ms for n, ms in per.items() if n not in INNER_ALL)
    print(f"live single frame: {1e3 * statistics.median(walls):.3f} ms wall (stages {stages:.3f}): {parts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
