"""One prepared check of `device="cuda"` on a machine with a GPU: correctness, then speed.

    python3 benchmarks/gpu_check.py [--size 1024] [--batch 32] [--quick]

Needs CuPy (pip install 'tirdeflect[gpu]') and an NVIDIA GPU; exits 2 with
the reason otherwise. Written without a GPU (issue 9): run it before trusting
any GPU figure, and put what it prints in docs/processing.md.

1. Correctness on ray-traced TIR frames (processing.forward): a dimple
   series deepening until its phase needs unwrapping and rays cross on its
   flank (masked frames: the CPU's part), a deep dimple (5 rad) alone
   (spatial unwrapping), travelling waves; full and decimated grids. The
   GPU's heights against the CPU Reconstructor's: max |dh| / RMS height
   must be <= 1e-3 (the issue's bar); also printed: the frames the GPU did.
2. Speed at --size (1024^2 default), against the CPU Reconstructor in the
   same run: batch frames/s on the full and decimated grids (goals >= 1000
   and >= 5000), live single-frame latency on the decimated grid (goal
   <= 3 ms), host-to-device copy included (frames start on the host as
   uint8, results end on the host).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TOL = 1e-3


def _render(surfaces, n, geometry, board):
    from processing import forward as F

    ref, _ = F.render_tir(F.FlatSurface(), geometry, (n, n), board, supersample=1)
    ref = F.quantize(ref, bits=8, noise_rms=0.0, rng=np.random.default_rng(99))
    frames = []
    for k, surface in enumerate(surfaces):
        img, _ = F.render_tir(surface, geometry, (n, n), board, supersample=1)
        frames.append(F.quantize(img, bits=8, noise_rms=0.5, rng=np.random.default_rng(k)))
    return ref, frames


def _cases(n, geometry):
    from processing import forward as F

    scale = n / 256.0
    board = F.Checkerboard(period_mm=2.0 * scale, edge_softness_mm=0.1 * scale)
    field = F.WaveField.random(6, amplitude_rms_mm=0.0002 * scale,
                               wavelength_range_mm=(n * 0.1 / 4, n * 0.1 / 2), seed=0)
    waves = F.TravellingWaves(field.components)
    return {
        "dimple series (unwrapping, folds)": _render(
            [F.Dimple((k + 1) * 0.0006 * scale, 3.2 * scale) for k in range(10)], n, geometry, board),
        "deep dimple (5 rad)": _render([F.Dimple(0.0045 * scale, n * 0.1 / 4.65)] * 3, n, geometry, board),
        "travelling waves": _render([waves.at(k / 200.0) for k in range(8)], n, geometry, board),
    }


def correctness(n, geometry) -> bool:
    from processing import Reconstructor
    from processing.gpu import ran_on_gpu

    ok = True
    for name, (ref, frames) in _cases(n, geometry).items():
        for grid in ("full", "decimated"):
            gpu = Reconstructor(ref, geometry, device="cuda")
            # the same options on the CPU (the GPU's refinement, FD's, resolved)
            cpu = Reconstructor(ref, geometry, gpu.options.replace(device="cpu"))
            expected = [cpu(f, grid=grid) for f in frames]
            got = gpu.batch(frames[:4], grid=grid) + gpu.batch(frames[4:], grid=grid)
            worst = 0.0
            masks = len(got) == len(expected)  # a frame lost on the way is a failure too
            for a, b in zip(expected, got):
                masks &= bool(np.array_equal(a.valid, b.valid))
                rms = float(np.sqrt(np.nanmean(a.height.astype(np.float64) ** 2)))
                worst = max(worst, float(np.nanmax(np.abs(a.height - b.height))) / rms)
            on_gpu = sum(map(ran_on_gpu, got))
            good = worst <= TOL and masks
            ok &= good
            print(f"{name:36s} {grid:9s} max|dh|/rms {worst:.1e}  "
                  f"masks {'same' if masks else 'DIFFER'} ({len(got)}/{len(expected)} frames)  "
                  f"{on_gpu}/{len(got)} frames on the GPU  {'PASS' if good else 'FAIL'}", flush=True)
    return ok


def speed(n, geometry, batch, rounds):
    import cupy

    from processing import Reconstructor
    from processing.gpu import ran_on_gpu

    ref, frames = _cases(n, geometry)["travelling waves"]
    order = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))  # small steps only
    stream = [frames[order[k % len(order)]] for k in range(batch * rounds)]
    print(f"\n{n} x {n}, batches of {batch}, {rounds} batches; device {cupy.cuda.runtime.getDeviceProperties(0)['name'].decode()}")
    verdicts = []
    for grid, goal in (("full", 1000.0), ("decimated", 5000.0)):
        cpu = Reconstructor(ref, geometry, planner_effort="FFTW_MEASURE", refine_method="fd")  # the GPU's chain
        cpu(stream[0], grid=grid)
        t0 = time.perf_counter()
        for f in stream[:batch]:
            cpu(f, grid=grid)
        cpu_fps = batch / (time.perf_counter() - t0)
        gpu = Reconstructor(ref, geometry, device="cuda")
        gpu.batch(stream[:batch], grid=grid, essentials=True)  # warm-up: kernels, plans
        cupy.cuda.Device().synchronize()
        t0 = time.perf_counter()
        done = on_gpu = 0
        for k in range(rounds):
            res = gpu.batch(stream[k * batch:(k + 1) * batch], grid=grid, essentials=True)
            done += len(res)
            on_gpu += sum(map(ran_on_gpu, res))
        fps = done / (time.perf_counter() - t0)
        verdicts.append(fps >= goal)
        print(f"batch {grid:9s}: GPU {fps:8.0f} frames/s ({1e3 / fps:.3f} ms/frame, {on_gpu}/{done} on the GPU)  "
              f"CPU {cpu_fps:6.1f} frames/s  ratio {fps / cpu_fps:6.1f}  goal >= {goal:.0f}: "
              f"{'PASS' if fps >= goal else 'FAIL'}", flush=True)
    gpu = Reconstructor(ref, geometry, device="cuda", grid="decimated")
    times = []
    for k in range(60):
        t0 = time.perf_counter()
        gpu(stream[k % len(stream)])
        times.append(time.perf_counter() - t0)
    latency = 1e3 * statistics.median(times[10:])
    verdicts.append(latency <= 3.0)
    print(f"live single frame (decimated): median {latency:.2f} ms  goal <= 3 ms: "
          f"{'PASS' if latency <= 3.0 else 'FAIL'}")
    return all(verdicts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="correctness at 256^2 only, no speed")
    args = ap.parse_args(argv)
    from processing import Geometry
    from processing.gpu import cupy_or_reason

    cupy, why = cupy_or_reason()
    if cupy is None:
        print(f"gpu_check: {why}", file=sys.stderr)
        return 2
    geometry = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    print("correctness against the CPU Reconstructor (max |dh| / RMS height <= 1e-3):")
    ok = correctness(256, geometry)
    if not args.quick:
        ok &= correctness(args.size, geometry) if args.size != 256 else True
        ok &= speed(args.size, geometry, args.batch, args.rounds)
    print("\ngpu_check:", "all PASS" if ok else "some FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
