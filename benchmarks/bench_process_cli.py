"""Throughput of `tirdeflect process` against the bare reconstruction, same run.

    python3 benchmarks/bench_process_cli.py [--size 1024] [--frames 12]

Baseline: ``Reconstructor`` called on frames already in memory. Measured: the
whole command (read a TIFF stack page by page, reconstruct, write and flush
OUT.h5 frame by frame). The ratio is the cost of files and crash safety.
Both use FFTW_ESTIMATE so planning does not blur the comparison.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args(argv)

    import tifffile

    from app.cli import main as cli_main
    from processing import Geometry, Reconstructor, forward
    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX, _sim_scene

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    pattern = forward.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm,
                                   edge_softness_mm=geometry.pixel_mm)
    scene = _sim_scene("waves", geometry, args.size, 2, 0)
    sim = forward.simulate(scene, geometry, (args.size, args.size), 2, pattern=pattern, supersample=1)
    frames = np.stack([sim.frames[k % 2] for k in range(args.frames)])

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        tifffile.imwrite(tmp / "ref.tif", sim.reference)
        tifffile.imwrite(tmp / "stack.tif", frames, photometric="minisblack")
        (tmp / "g.toml").write_text(geometry.to_toml_text())

        rec = Reconstructor(sim.reference, geometry, planner_effort="FFTW_ESTIMATE")
        rec(frames[0])  # warm-up
        t0 = time.perf_counter()
        for f in frames:
            rec(f)
        base = (time.perf_counter() - t0) / len(frames)

        t0 = time.perf_counter()
        code = cli_main(["process", str(tmp / "ref.tif"), str(tmp / "stack.tif"), "--geometry",
                         str(tmp / "g.toml"), "--out", str(tmp / "out.h5"), "--no-progress",
                         "--fft-effort", "estimate"])
        whole = time.perf_counter() - t0
        assert code == 0
    # the command's fixed cost (reference analysis, file creation) is in `whole`
    per_frame = whole / len(frames)
    print(f"{args.size} x {args.size}, {args.frames} frames, full grid")
    print(f"baseline Reconstructor in memory: {base * 1e3:8.1f} ms/frame")
    print(f"tirdeflect process (files, flush): {per_frame * 1e3:8.1f} ms/frame incl. start-up")
    print(f"ratio process / baseline: {per_frame / base:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
