"""The window's live path on a GPU, without the window: what *View > Live reconstruction
on the GPU* runs, checked against the CPU and timed.

    python3 benchmarks/gpu_live_check.py [--size 1024] [--frames 60]

The window builds ``Reconstructor(reference, geometry, device="cuda")`` and its worker
sends each frame to the live worker process (app/capture/live_process.py), which
rebuilds that reconstructor from its picklable recipe and runs
:func:`app.capture.live_measure.measure_live`. Here the same LiveProcess measures the
app's own scene (app/capture/scene.py: the synthetic camera's ray-traced frames, every
3rd frame as a busy window takes them), and a CPU Reconstructor with the same options
measures the same frames in the same order. Then the same for travelling waves valid everywhere
(gpu_check's), the GPU chain's own ground. Printed per scene: how many frames the GPU
did (a frame with masked samples goes to the CPU), max |dh| / RMS height against the
CPU (bar 1e-3, masks equal), and the median wall time of a live frame (the child's
reconstruction, and the round trip through shared memory and the pipe) for the GPU and
the CPU worker process in the same run.
Needs CuPy and a GPU (or NumPy named cupy, tests/processing/numpy_cupy, for a dry run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TOL = 1e-3


def _live(rec, reference, frames, order):
    """Measured results of ``frames[order]`` through a LiveProcess, and the round trips (s)."""
    from app.capture.live_measure import LiveJob
    from app.capture.live_process import LiveProcess

    live = LiveProcess()
    stop = threading.Event()
    out, trips, inside = [], [], []
    try:
        for j, k in enumerate(order):
            t0 = time.perf_counter()
            m = live.measure(rec, reference, frames[k], LiveJob("decimated", j == 0, False), stop)
            trips.append(time.perf_counter() - t0)
            inside.append(m.processing_s)
            out.append(m)
    finally:
        live.close()
    return out, trips, inside


def check(name, reference, geometry, frames, order) -> bool:
    """One scene through the live worker process on the GPU, then on the CPU: printed, PASS or not."""
    from processing import Reconstructor
    from processing.gpu import ran_on_gpu

    gpu = Reconstructor(reference, geometry, device="cuda")  # as app/gui/reference_flow.py builds it
    print(f"{name}: {len(order)} live frames; device cuda: {gpu.gpu_fallback or 'the GPU chain'}", flush=True)
    measured, trips, inside = _live(gpu, reference, frames, order)
    cpu = Reconstructor(reference, geometry, gpu.options.replace(device="cpu"))
    worst, same_masks, errors, on_gpu = 0.0, True, 0, 0
    for j, (m, k) in enumerate(zip(measured, order)):
        if j == 0:
            cpu.reset_series()
        expected = cpu(frames[k], grid="decimated")
        if m.result is None:
            errors += 1
            print(f"  frame {k}: {m.error}")
            continue
        on_gpu += ran_on_gpu(m.result)
        same_masks &= bool(np.array_equal(m.result.valid, expected.valid))
        both = m.result.valid & expected.valid
        rms = float(np.sqrt(np.mean(expected.height[both].astype(np.float64) ** 2)))
        worst = max(worst, float(np.max(np.abs(m.result.height[both] - expected.height[both]))) / rms)
    ok = errors == 0 and same_masks and worst <= TOL
    print(f"  heights against the CPU: max|dh|/rms {worst:.1e}, masks {'same' if same_masks else 'DIFFER'}, "
          f"{errors} errors, {on_gpu}/{len(measured)} frames on the GPU: {'PASS' if ok else 'FAIL'}", flush=True)
    _, cpu_trips, cpu_inside = _live(cpu, reference, frames, order)
    med = lambda v: 1e3 * statistics.median(v[10:] or v)  # noqa: E731 - after the warm-up
    print(f"  live frame in the worker process: GPU {med(inside):.1f} ms reconstruction, {med(trips):.1f} ms "
          f"round trip; CPU {med(cpu_inside):.1f} / {med(cpu_trips):.1f} ms; ratio {med(cpu_trips) / med(trips):.2f}",
          flush=True)
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from gpu_check import _cases

    from app.capture.scene import build_scene
    from processing import Geometry
    from processing.gpu import cupy_or_reason

    cupy, why = cupy_or_reason()
    if cupy is None:
        print(f"gpu_live_check: {why}", file=sys.stderr)
        return 2
    n = args.size
    sim, geometry = build_scene((n, n), 48, frame_rate_hz=100)
    ok = check(f"{n}^2 app scene (every 3rd of 48 frames)", sim.reference, geometry, sim.frames,
               [(3 * j) % len(sim.frames) for j in range(args.frames)])
    g55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    ref, frames = _cases(n, g55)["travelling waves"]  # valid everywhere: the GPU chain's own ground
    back_and_forth = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    ok &= check(f"{n}^2 travelling waves (valid everywhere)", ref, g55, frames,
                [back_and_forth[j % len(back_and_forth)] for j in range(args.frames)])
    print("\ngpu_live_check:", "PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
