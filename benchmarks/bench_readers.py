"""Reading frames from Photron MRAW and lossless AVI against the app's own HDF5
recording, read-only and through the whole `tirdeflect process`, same run.

    python3 benchmarks/bench_readers.py                 # 1024^2 x 160 frames, 2 rounds (minutes)
    python3 benchmarks/bench_readers.py --no-process    # read-only figures only (~20 s)
    python3 benchmarks/bench_readers.py --frames 1000   # the issue's length; OUT.h5 is ~13 GB
                                                        # per run (deleted after each), in --tmp

Baseline: the app's HDF5 recording (``/frames`` chunked one frame per chunk, as
``app.capture.recorder`` writes it). Measured: the same 12-bit frames as a 16-bit
MRAW + CIH written by pyMRAW, and two lossless ``gray16le`` AVIs written by
PyAV with FFmpeg's defaults: FFV1 (range coder, a keyframe every 12 frames;
the smallest file) and FFVHuff (Huffman coded, every frame a keyframe).

- "read" is ``imageio.iter_frames`` alone (the one reader `tirdeflect process`
  uses), every frame in order;
- "process" is ``tirdeflect process`` (``app.cli`` -> ``app.batch.run_process``)
  with FFTW_ESTIMATE on the same frames, OUT.h5 writing included. With 64
  frames or more it runs its worker processes (one per core), each reading
  its own chunk of the file (video: seek to the keyframe before the chunk),
  as it does for a 1000-frame recording.

Each figure is frames/s, and the CPU time it cost per frame (all threads and
worker processes): read-only, that is what decoding costs. `tirdeflect process`
keeps every core busy (one worker per core), so decoding's CPU time comes off
processing: "CPU ratio" (HDF5's process CPU per frame over the input's) is
the frames/s ratio to expect when the cores are the limit, and it
does not move with other programs' load as the wall-clock ratio does.
Inputs are measured in rounds, the order reversed every round (A B C C B A)
so that a load that changes during the run weighs on all of them alike;
ratios are against the HDF5 recording measured in the same run. The machine
load (``/proc/loadavg``) is printed before and after: other programs' load
moves single figures by tens of per cent.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _write_inputs(tmp: Path, reference, frames_of, n: int):
    import av
    import h5py
    import pyMRAW

    rows, cols = reference.shape
    with h5py.File(tmp / "rec.h5", "w") as f:
        ds = f.create_dataset("frames", shape=(n, rows, cols), chunks=(1, rows, cols), dtype=np.uint16)
        for k in range(n):
            ds[k] = frames_of(k)
        f.create_dataset("reference", data=reference)
    # pyMRAW's writer takes an array (or a list) of frames; write in blocks to bound memory
    block = 50
    _, cih = pyMRAW.save_mraw(np.stack([frames_of(k) for k in range(min(n, block))]),
                              str(tmp / "rec.cih"), bit_depth=16, info_dict={"Record Rate(fps)": 1000})
    if n > block:
        with open(tmp / "rec.mraw", "ab") as fh:
            for k in range(block, n):
                frames_of(k).astype("<u2").tofile(fh)
        text = Path(cih).read_text()
        Path(cih).write_text(text.replace(f"Total Frame : {block}", f"Total Frame : {n}")
                             .replace(f"Original Total Frame : {block}", f"Original Total Frame : {n}"))
    for codec in ("ffv1", "ffvhuff"):
        with av.open(str(tmp / f"rec_{codec}.avi"), "w") as c:
            s = c.add_stream(codec, rate=1000)
            s.width, s.height, s.pix_fmt = cols, rows, "gray16le"
            for k in range(n):
                for p in s.encode(av.VideoFrame.from_ndarray(frames_of(k), format="gray16le")):
                    c.mux(p)
            for p in s.encode():
                c.mux(p)
    return {"hdf5": tmp / "rec.h5", "mraw": Path(cih), "ffv1": tmp / "rec_ffv1.avi",
            "ffvhuff": tmp / "rec_ffvhuff.avi"}


def _cpu_s() -> float:
    """CPU seconds of this process (all its threads) and of its ended children."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        r = resource.getrusage(who)
        total += r.ru_utime + r.ru_stime
    return total


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def _measure(work, frames: int) -> tuple:
    """(seconds, CPU seconds) of ``work()``, which handles ``frames`` frames."""
    c0, t0 = _cpu_s(), time.perf_counter()
    work()
    return time.perf_counter() - t0, _cpu_s() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--rounds", type=int, default=2, help="measurements of each input (order reversed each round)")
    ap.add_argument("--no-process", action="store_true", help="read-only figures only")
    ap.add_argument("--tmp", default=None, help="folder for the files (default: system temp)")
    args = ap.parse_args(argv)

    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX, _sim_scene
    from app.cli import main as cli_main
    from app.files import imageio
    from processing import Geometry, forward

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    pattern = forward.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm,
                                   edge_softness_mm=geometry.pixel_mm)
    scene = _sim_scene("waves", geometry, args.size, 2, 0)
    sim = forward.simulate(scene, geometry, (args.size, args.size), 2, pattern=pattern,
                           supersample=1, bits=12)
    reference = np.asarray(sim.reference, dtype=np.uint16)
    pair = [np.asarray(f, dtype=np.uint16) for f in sim.frames]

    def frames_of(k):
        return pair[k % 2]

    print(f"load before: {_loadavg()} (1, 5, 15 min) on {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        inputs = _write_inputs(tmp, reference, frames_of, args.frames)
        print(f"{args.size} x {args.size} x {args.frames} frames (12-bit samples in uint16); "
              f"inputs written in {time.perf_counter() - t0:.1f} s")
        for name, path in inputs.items():
            data = path.with_suffix(".mraw") if name == "mraw" else path
            print(f"  {name:8s} {data.stat().st_size / 2**20:8.1f} MiB")
        (tmp / "g.toml").write_text(geometry.to_toml_text())
        imageio.write_image(tmp / "ref.tif", reference)

        def read_all(path):
            n = 0
            for item in imageio.iter_frames([path]):
                n += 1
                assert item.image.shape == reference.shape
            assert n == args.frames

        def process(path, out):
            with contextlib.redirect_stderr(io.StringIO()) as err:
                code = cli_main(["process", str(tmp / "ref.tif"), str(path), "--geometry", str(tmp / "g.toml"),
                                 "--out", str(out), "--no-progress", "--fft-effort", "estimate"])
            if code != 0:
                raise SystemExit(f"process {path.name} failed:\n{err.getvalue()}")
            out.unlink()

        names = list(inputs)
        rounds = [names if r % 2 == 0 else names[::-1] for r in range(args.rounds)]
        for path in inputs.values():  # warm: imports, page cache
            imageio.read_image(path, index=0)
        read = {name: [0.0, 0.0] for name in names}
        for order in rounds:
            for name in order:
                wall, cpu = _measure(lambda: read_all(inputs[name]), args.frames)
                read[name][0] += wall
                read[name][1] += cpu
        proc = {}
        if not args.no_process:
            # warm-up (imports, FFTW plans) so that the first input measured is not penalised
            with contextlib.redirect_stderr(io.StringIO()):
                cli_main(["process", str(tmp / "ref.tif"), str(inputs["hdf5"]), "--frames", ":3",
                          "--geometry", str(tmp / "g.toml"), "--out", str(tmp / "warm.h5"),
                          "--no-progress", "--fft-effort", "estimate"])
            proc = {name: [0.0, 0.0] for name in names}
            for order in rounds:
                for name in order:
                    wall, cpu = _measure(lambda: process(inputs[name], tmp / f"out_{name}.h5"), args.frames)
                    proc[name][0] += wall
                    proc[name][1] += cpu

    n = args.frames * args.rounds
    head = f"{'input':8s} {'read frames/s':>13s} {'ratio':>6s} {'CPU ms/frame':>12s}"
    if proc:
        head += f" {'process frames/s':>16s} {'ratio':>6s} {'CPU ms/frame':>12s} {'CPU ratio':>9s}"
    print(head)
    for name in names:
        fps = n / read[name][0]
        line = f"{name:8s} {fps:13.1f} {fps / (n / read['hdf5'][0]):6.2f} {1e3 * read[name][1] / n:12.1f}"
        if proc:
            fps = n / proc[name][0]
            line += (f" {fps:16.2f} {fps / (n / proc['hdf5'][0]):6.2f} {1e3 * proc[name][1] / n:12.1f}"
                     f" {proc['hdf5'][1] / proc[name][1]:9.2f}")
        print(line)
    print(f"ratios against the app's HDF5 recording, measured in this run ({args.rounds} rounds of "
          f"{args.frames} frames per input); load after: {_loadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
