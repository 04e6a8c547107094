"""Reading frames from Photron MRAW and lossless AVI against the app's own HDF5
recording, read-only and through the whole `tirdeflect process`, same run.

    python3 benchmarks/bench_readers.py                       # 512^2 x 60 frames (about a minute)
    python3 benchmarks/bench_readers.py --size 1024 --frames 1000 --no-process
    python3 benchmarks/bench_readers.py --size 1024 --frames 1000   # the issue's case; OUT.h5
                                                                    # needs ~13 GB in --tmp

Baseline: the app's HDF5 recording (``/frames`` chunked one frame per chunk, as
``app.capture.recorder`` writes it). Measured: the same 12-bit frames as a 16-bit
MRAW + CIH written by pyMRAW and an FFV1 ``gray16le`` AVI written by PyAV.
"read" is ``imageio.iter_frames`` alone (frames/s); "process" is
``tirdeflect process`` with FFTW_ESTIMATE on the same frames, file writing
included. Reading must not be the bottleneck: process frames/s should be the
same for all three (ratio ~1.00).
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
    with av.open(str(tmp / "rec.avi"), "w") as c:
        s = c.add_stream("ffv1", rate=1000)
        s.width, s.height, s.pix_fmt = cols, rows, "gray16le"
        for k in range(n):
            for p in s.encode(av.VideoFrame.from_ndarray(frames_of(k), format="gray16le")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return {"hdf5": tmp / "rec.h5", "mraw": Path(cih), "avi": tmp / "rec.avi"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=60)
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

    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        inputs = _write_inputs(tmp, reference, frames_of, args.frames)
        print(f"{args.size} x {args.size} x {args.frames} frames (12-bit samples in uint16); "
              f"inputs written in {time.perf_counter() - t0:.1f} s")
        for name, path in inputs.items():
            data = path.with_suffix(".mraw") if name == "mraw" else path
            print(f"  {name:5s} {data.stat().st_size / 2**20:8.1f} MiB")
        (tmp / "g.toml").write_text(geometry.to_toml_text())
        imageio.write_image(tmp / "ref.tif", reference)
        imageio.read_reference(tmp / "rec.h5")  # warm the imports
        read = {}
        for name, path in inputs.items():
            t0 = time.perf_counter()
            n = 0
            for item in imageio.iter_frames([path]):
                n += 1
                assert item.image.shape == reference.shape
            read[name] = n / (time.perf_counter() - t0)
        proc = {}
        if not args.no_process:
            # warm-up (imports, FFTW plans) so that the first input measured is not penalised
            cli_main(["process", str(tmp / "ref.tif"), str(inputs["hdf5"]), "--frames", ":3",
                      "--geometry", str(tmp / "g.toml"), "--out", str(tmp / "warm.h5"),
                      "--no-progress", "--fft-effort", "estimate"])
            for name, path in inputs.items():
                out = tmp / f"out_{name}.h5"
                t0 = time.perf_counter()
                code = cli_main(["process", str(tmp / "ref.tif"), str(path), "--geometry", str(tmp / "g.toml"), "--out", str(out),
                                 "--no-progress", "--fft-effort", "estimate"])
                proc[name] = args.frames / (time.perf_counter() - t0)
                assert code == 0
                out.unlink()
    print(f"{'input':6s} {'read frames/s':>14s} {'ratio':>6s}" +
          ("" if args.no_process else f" {'process frames/s':>17s} {'ratio':>6s}"))
    for name in read:
        line = f"{name:6s} {read[name]:14.1f} {read[name] / read['hdf5']:6.2f}"
        if proc:
            line += f" {proc[name]:17.2f} {proc[name] / proc['hdf5']:6.2f}"
        print(line)
    print("ratios against the app's HDF5 recording, measured in this run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
