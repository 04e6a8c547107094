"""Frames/s of `tirdeflect process` on a 1024^2 recording against worker processes and Dask.

    python3 benchmarks/bench_scale.py [--size 1024] [--frames 96] [--max-workers N] [--no-dask]

One HDF5 recording (ray-traced travelling waves, full grid, FFTW_ESTIMATE so
that planning does not blur the comparison) is processed by the batch engine
(what `tirdeflect process` runs) with --workers 1 (the baseline, in this
process), 2, ... up to the core count, then through --dask local:N. Each
line prints frames/s over the whole run (start-up included) and in steady
state (from the first frame written to the last), and the speed-up against
the baseline measured in this run. The goal of issue 9: >= 0.8 N at N workers.
The load of the machine (1-minute load average before each run) is printed:
on a shared machine the figures are only as good as the cores that were free.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _recording(tmp: Path, size: int, n_frames: int):
    import h5py

    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX, _sim_scene
    from processing import Geometry, forward

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    pattern = forward.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm,
                                   edge_softness_mm=geometry.pixel_mm)
    n_distinct = 4
    scene = _sim_scene("waves", geometry, size, n_distinct, 0)
    sim = forward.simulate(scene, geometry, (size, size), n_distinct, pattern=pattern, supersample=1)
    path = tmp / "recording.h5"
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("frames", shape=(n_frames, size, size), dtype=sim.frames[0].dtype,
                              chunks=(1, size, size))
        for k in range(n_frames):
            ds[k] = sim.frames[k % n_distinct]
        f.create_dataset("reference", data=sim.reference)
        f["geometry_toml"] = geometry.to_toml_text()
    return path


def _run(path: Path, out: Path, **kw):
    from app.batch import ProcessJob, run_process

    stamps = []
    job = ProcessJob(reference=str(path), frames=[str(path)], out=str(out), overwrite=True,
                     fft_effort="estimate", on_progress=lambda done, total: stamps.append(time.perf_counter()),
                     **kw)
    t0 = time.perf_counter()
    report = run_process(job)
    whole = time.perf_counter() - t0
    n = report.frames_written
    steady = (n - 1) / (stamps[-1] - stamps[0]) if n > 1 and stamps[-1] > stamps[0] else float("nan")
    return n / whole, steady


def main(argv=None) -> int:
    from app.batch.parallel import available_cores

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--max-workers", type=int, default=available_cores())
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args(argv)

    cores = available_cores()
    print(f"{args.size} x {args.size}, {args.frames} frames, full grid, {cores} core(s) available "
          f"({os.cpu_count()} in the machine)")
    counts = sorted({1, *range(2, args.max_workers + 1)})
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = _recording(tmp, args.size, args.frames)
        rows = []
        base = None
        runs = [("workers", n, dict(workers=n)) for n in counts]
        if not args.no_dask:
            try:
                import distributed  # noqa: F401

                runs += [("dask local", n, dict(dask=f"local:{n}")) for n in counts]
            except ImportError:
                print("(dask not installed: pip install 'tirdeflect[dask]' for the --dask rows)")
        for what, n, kw in runs:
            load = os.getloadavg()[0]
            whole, steady = _run(path, tmp / "out.h5", **kw)
            if base is None:
                base = (whole, steady)
            rows.append((what, n, load, whole, steady))
            print(f"{what:10s} N={n:2d}  load {load:5.2f}  {whole:6.1f} frames/s whole run "
                  f"(x{whole / base[0]:.2f})  {steady:6.1f} frames/s steady (x{steady / base[1]:.2f}, "
                  f"goal >= {0.8 * n:.1f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
