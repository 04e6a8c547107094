"""What the per-frame CRC32 of recording format 1.2 costs the recorder's writes.

Writes the same 1024 x 1024 uint8 frames through ``RecordingFile`` (as
``bench_acquisition.py``'s throughput step) twice in one run, alternately, with
the recorder's checksum and with it replaced by a constant, and prints the
write rates and their ratio (same-run ratio: the machine's load cancels).

    python benchmarks/bench_recorder_crc.py --mb 400 --trials 3 [--tmp DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.capture import recorder  # noqa: E402

SHAPE = (1024, 1024)


def write_rate_mb_s(folder: Path, n_frames: int, frames) -> float:
    path = folder / "bench-crc.h5"
    rf = recorder.RecordingFile(path, shape=SHAPE, dtype=np.uint8, n_frames=n_frames, check_space=False)
    t0 = time.perf_counter()
    for i in range(n_frames):
        rf.write(frames[i % len(frames)], (i, i, i, i, 0, i))
    rf.close()
    wall = time.perf_counter() - t0
    os.remove(path)
    return n_frames * frames[0].nbytes / wall / 1e6


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mb", type=float, default=400.0, help="data written per trial, MB")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--tmp", default=None, help="folder for the files (default: system temp)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, SHAPE, dtype=np.uint8) for _ in range(4)]
    n = max(1, int(args.mb * 1e6 / frames[0].nbytes))
    real_crc32 = recorder.zlib.crc32
    rates = {"crc32": [], "none": []}
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        for _ in range(args.trials):
            for mode in ("crc32", "none"):
                recorder.zlib.crc32 = real_crc32 if mode == "crc32" else (lambda data: 0)
                try:
                    rates[mode].append(write_rate_mb_s(Path(tmp), n, frames))
                finally:
                    recorder.zlib.crc32 = real_crc32
    best = {mode: max(values) for mode, values in rates.items()}
    print(f"recorder writes, {n} frames of 1024x1024 uint8, best of {args.trials}: "
          f"with CRC32 {best['crc32']:.0f} MB/s, without {best['none']:.0f} MB/s, "
          f"ratio {best['crc32'] / best['none']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
