"""Frames/s of `tirdeflect process` on a 1024^2 recording against worker processes and Dask.

    python3 benchmarks/bench_scale.py [--size 1024] [--frames 96] [--max-workers N] [--no-dask]
    python3 benchmarks/bench_scale.py --writer [--baseline-rev REV] [--compression gzip] [--rounds 2] [--out-dir DIR]
    python3 benchmarks/bench_scale.py --default-vs [REV] [--frames 1000] [--rounds 1]
    python3 benchmarks/bench_scale.py --refine-vs [--frames 200] [--rounds 2]

One HDF5 recording (ray-traced travelling waves, full grid, FFTW_ESTIMATE so
that planning does not blur the comparison) is processed by the batch engine
(what `tirdeflect process` runs) with --workers 1 (the baseline, in this
process), 2, ... up to the core count, then through --dask local:N. Each
line prints frames/s over the whole run (start-up included) and in steady
state (from the first frame written to the last), the speed-up against
the baseline measured in this run, and the CPU time of the run's own
process per frame in steady state ("parent": reading, writing OUT.h5, and
with --workers 1 the reconstruction too; the workers' CPU is not in it). The goal of issue 9:
>= 0.8 N at N workers. The load of the machine (1-minute load average
before each run) is printed: on a shared machine the figures are only as
good as the cores that were free.

--writer compares the writer of OUT.h5, rounds of runs in turn, each in a
fresh process: this tree as it is (flush every 0.5 s, NaN mask and
compression in the workers, maps written from shared memory), this tree
flushing after every frame (writer.FLUSH_INTERVAL_S = 0), and with
--baseline-rev the code of that git revision (e.g. the commit before the
change), for --workers 1 and 2, all with FD's refinement (--refine fd: the
trees before the image refinement know no other), so that only the writer
differs.

--default-vs (issue 22) times what a user's `tirdeflect process IN -o OUT`
does by default (the batch engine's ProcessJob with nothing but its input
and output: every core, the default refinement, the default FFT planning)
on --frames frames (1,000 for the issue's figure), with this tree and with
the code of REV (default: DEFAULT_VS_REV, the code before issue 22's speed
work), each in a fresh process, in turn: the wall time of the whole run and
the ratio, same recording, same machine, same minutes.

--refine-vs (issue 22) times that default against `tirdeflect process --refine fd` (the same
but for FD's refinement), both on every core as the command runs them (one frame per worker
process, one thread each), fresh processes in turn: the steady rates and their ratio.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
#: --writer's children run the code of another tree; their spawned workers, which run this
#: file again as their main module, must import that tree too
TREE = os.environ.get("TIRDEFLECT_BENCH_TREE", str(ROOT))
sys.path.insert(0, TREE)


#: The code before issue 22's speed work (docs/processing.md section 6: "cc879fb, the code before this
#: work"): what --default-vs compares this tree's default `process` with.
DEFAULT_VS_REV = "cc879fb"


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
    """(frames/s whole run, frames/s steady, CPU ms per frame of this process in steady state,
    from the first frame written to the last: start-up, FFT plans and the final close left out)."""
    from app.batch import ProcessJob, run_process

    stamps = []
    if kw.pop("defaults", False):  # what `tirdeflect process IN -o OUT` runs: the job's own defaults
        kw = {k: v for k, v in kw.items() if k == "refine_method"}  # (--refine-vs: but for the refinement)
    else:
        kw = {"fft_effort": "estimate", **kw}
    job = ProcessJob(reference=str(path), frames=[str(path)], out=str(out), overwrite=True,
                     on_progress=lambda done, total: stamps.append((time.perf_counter(), time.process_time())),
                     **kw)
    t0 = time.perf_counter()
    report = run_process(job)
    whole = time.perf_counter() - t0
    n = report.frames_written
    (t_first, c_first), (t_last, c_last) = stamps[0], stamps[-1]
    steady = (n - 1) / (t_last - t_first) if n > 1 and t_last > t_first else float("nan")
    cpu = 1e3 * (c_last - c_first) / (n - 1) if n > 1 else float("nan")
    return n / whole, steady, cpu


def _child(spec: str) -> int:
    """One run in this process, with the code of spec["tree"]: prints its figures as JSON."""
    import json

    spec = json.loads(spec)
    import app
    from app.batch import ProcessJob

    if "refine_method" in ProcessJob.__dataclass_fields__ and not spec["job"].get("defaults"):
        # the same reconstruction in every tree: FD's (trees before the image refinement)
        spec["job"].setdefault("refine_method", "fd")

    assert Path(app.__file__).resolve().parent.parent == Path(spec["tree"]).resolve(), app.__file__
    if spec.get("flush_every_frame"):
        import app.batch.writer

        app.batch.writer.FLUSH_INTERVAL_S = 0.0
    print(json.dumps(_run(Path(spec["path"]), Path(spec["out"]), **spec["job"])))
    return 0


def _tree_of(rev: str, tmp: Path) -> str:
    """The files of git revision ``rev`` of this repository, extracted under ``tmp``."""
    import subprocess

    base = tmp / f"rev-{rev}"
    base.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
    return str(base)


def _in_child(tree: str, spec: dict):
    """``(whole, steady, cpu)`` of one run of ``spec`` by the code of ``tree`` in a fresh process, or
    the tail of its error output (str) where it failed."""
    import json
    import subprocess

    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(dict(spec, tree=tree))], cwd=tree,
                          capture_output=True, text=True, env=dict(os.environ, TIRDEFLECT_BENCH_TREE=tree))
    if proc.returncode != 0:
        return proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _alternating(args, path: Path, tmp: Path, runs) -> dict:
    """``{name: [(wall s, frames/s whole run, frames/s steady), ...]}`` of ``runs`` (``(name, tree, job)``)
    in fresh processes, ``args.rounds`` rounds in alternating order, each line printed."""
    got_all = {}
    for r in range(args.rounds):
        for name, tree, job in runs[r % 2:] + runs[:r % 2]:  # order alternates
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            got = _in_child(tree, dict(path=str(path), out=str(tmp / "out.h5"), job=job))
            wall = time.perf_counter() - t0
            if isinstance(got, str):
                print(f"{name}: failed\n{got}")
                continue
            got_all.setdefault(name, []).append((wall, got[0], got[1]))
            print(f"round {r}  {name:16s} load {load:5.2f}  wall {wall:7.1f} s (process start included)  "
                  f"{got[0]:6.2f} frames/s whole run  {got[1]:6.2f} frames/s steady", flush=True)
    return got_all


def _default_vs(args, path: Path, tmp: Path) -> None:
    """Issue 22: `tirdeflect process` by default, this tree against the code of ``args.default_vs``."""
    runs = [("this tree", str(ROOT), dict(defaults=True)),
            (f"rev {args.default_vs}", _tree_of(args.default_vs, tmp), dict(defaults=True))]
    print(f"`tirdeflect process` by default (every core, default refinement and FFT planning), "
          f"{args.frames} frames; this tree against the code of {args.default_vs}, fresh processes in turn")
    got = _alternating(args, path, tmp, runs)
    mine, old = (min([g[0] for g in got.get(name, [])], default=math.nan) for name, _, _ in runs)
    print(f"best wall time: this tree {mine:.1f} s, rev {args.default_vs} {old:.1f} s: "
          f"x{old / mine:.2f} faster (goal of issue 22: >= 3x)")


def _refine_vs(args, path: Path, tmp: Path) -> None:
    """Issue 22: `tirdeflect process` by default against `tirdeflect process --refine fd`, both as a user
    runs them (every core: one frame per worker process, one thread each), fresh processes in turn."""
    runs = [("default", str(ROOT), dict(defaults=True)),
            ("--refine fd", str(ROOT), dict(defaults=True, refine_method="fd"))]
    print(f"`tirdeflect process` by default against `--refine fd` (every core, default FFT planning), "
          f"{args.frames} frames, fresh processes in turn; steady: from the first frame written to the last")
    got = _alternating(args, path, tmp, runs)
    best = {name: max([g[2] for g in got.get(name, [])], default=math.nan) for name, _, _ in runs}
    print(f"best steady rate: default {best['default']:.2f}, --refine fd {best['--refine fd']:.2f} frames/s: "
          f"the default takes x{best['--refine fd'] / best['default']:.2f} FD's time "
          f"(goal of issue 22: <= 2.5x)")


def _writer_rounds(args, path: Path, tmp: Path) -> None:
    """The writer of OUT.h5: this tree, this tree flushing every frame, --baseline-rev."""
    trees = [("this tree", str(ROOT), False), ("flush every frame", str(ROOT), True)]
    if args.baseline_rev:
        trees.append((f"rev {args.baseline_rev}", _tree_of(args.baseline_rev, tmp), False))
    where = args.out_dir or "a temporary directory"
    print(f"writer of OUT.h5, compression {args.compression}, written to {where}; 'parent CPU': CPU "
          f"time of the process that writes, per frame")
    figures = {}
    out_dir = Path(args.out_dir) if args.out_dir else tmp
    for r in range(args.rounds):
        for n in (1, 2):
            for name, tree, every in trees[r % len(trees):] + trees[:r % len(trees)]:  # order rotates
                job = dict(workers=n, compression=args.compression)
                spec = dict(flush_every_frame=every, path=str(path), out=str(out_dir / "out.h5"), job=job)
                load = os.getloadavg()[0]
                got = _in_child(tree, spec)
                if isinstance(got, str):
                    print(f"{name}: failed\n{got}")
                    continue
                whole, steady, cpu = got
                figures.setdefault((n, name), []).append(cpu)
                print(f"round {r}  workers {n}  {name:20s} load {load:5.2f}  {whole:6.1f} frames/s whole run  "
                      f"{steady:6.1f} frames/s steady  parent CPU {cpu:6.1f} ms/frame", flush=True)
    for n in (1, 2):
        ref = figures.get((n, trees[-1][0]))
        for name, _, _ in trees:
            cpu = figures.get((n, name))
            if cpu and ref:
                print(f"workers {n}  {name:20s} parent CPU {min(cpu):6.1f} ms/frame (best of {len(cpu)}), "
                      f"x{min(cpu) / min(ref):.2f} of {trees[-1][0]}")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:  # before anything imports app: the child picks its tree
        return _child(argv[1])
    from app.batch.parallel import available_cores

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--max-workers", type=int, default=available_cores())
    ap.add_argument("--no-dask", action="store_true")
    ap.add_argument("--writer", action="store_true", help="compare the writer of OUT.h5 (see above)")
    ap.add_argument("--baseline-rev", help="with --writer: also the code of this git revision")
    ap.add_argument("--compression", default="none", choices=("none", "gzip", "lzf"))
    ap.add_argument("--default-vs", nargs="?", const=DEFAULT_VS_REV, metavar="REV",
                    help=f"issue 22: default `process`, this tree against REV (default {DEFAULT_VS_REV})")
    ap.add_argument("--refine-vs", action="store_true",
                    help="issue 22: `process` by default against `process --refine fd`, every core (see above)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out-dir", help="with --writer: write OUT.h5 there (e.g. /dev/shm: no disk "
                                      "write-back in the figures); default: a temporary directory")
    args = ap.parse_args(argv)

    cores = available_cores()
    print(f"{args.size} x {args.size}, {args.frames} frames, full grid, {cores} core(s) available "
          f"({os.cpu_count()} in the machine)")
    counts = sorted({1, *range(2, args.max_workers + 1)})
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = _recording(tmp, args.size, args.frames)
        if args.writer:
            _writer_rounds(args, path, tmp)
            return 0
        if args.default_vs:
            _default_vs(args, path, tmp)
            return 0
        if args.refine_vs:
            _refine_vs(args, path, tmp)
            return 0
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
            whole, steady, cpu = _run(path, tmp / "out.h5", compression=args.compression, **kw)
            if base is None:
                base = (whole, steady)
            rows.append((what, n, load, whole, steady))
            print(f"{what:10s} N={n:2d}  load {load:5.2f}  {whole:6.1f} frames/s whole run "
                  f"(x{whole / base[0]:.2f})  {steady:6.1f} frames/s steady (x{steady / base[1]:.2f}, "
                  f"goal >= {0.8 * n:.1f})  parent CPU {cpu:5.1f} ms/frame", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
