"""`tirdeflect process` over several processes and on Dask gives the heights of a serial run.

The series: a ray-traced dimple deepening to a carrier phase of 9 rad, and
from frame 5 on a ring of the pattern goes blank (no contrast: masked)
around the flank where the phase is largest. The island inside the ring
carries phase beyond pi: unwrapped in space alone it is off by 2 pi (frames
5-7), so a chunk whose overlap frame is frame 5 starts wrong and must be
caught by the consistency check and redone in time.
"""

import logging
import os
import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.batch import ProcessJob, run_process
from app.batch import parallel
from app.cli import main
from app.files import imageio
from processing.errors import TirdeflectError
from tests.helpers import stderr_until_signalled, worker_processes

SIZE = 256
N_FRAMES = 12
RING_FROM = 5  # first frame with the blank ring

# Heights of the same frame through different FFT plans/threads differ by float32
# rounding, which the batch default's image matching (processing/dic.py) amplifies:
# cv2.remap places pixels in 1/32 px steps, so the matched optimum moves in steps.
# Measured, serial against 2 workers (a killed one replaced): height 3.5e-5 of its
# peak, slope_x 3.1e-4, slope_y 2.3e-4 (2.1e-5 / 2.1e-4 / 1.4e-4 before FD's warp,
# the start of image matching, was made exact in the carriers). A 2 pi unwrapping
# slip on the island moves them by ~2 % of the peak. 1e-3 of the peak separates the
# two: 3x above the rounding, 20x below a slip.
REL_TOL = 1e-3


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("dimple")
    code = main(["simulate", "--out", str(d), "--surface", "dimple", "--size", str(SIZE),
                 "--frames", str(N_FRAMES), "--max-phase", "9"])
    assert code == 0
    yy, xx = np.mgrid[:SIZE, :SIZE]
    ring = (np.hypot(yy - 150, xx - 134) > 24) & (np.hypot(yy - 150, xx - 134) < 34)
    frames = []
    for k in range(N_FRAMES):
        image = imageio.read_image(d / f"frame_{k:04d}.png")
        if k >= RING_FROM:
            image = image.copy()
            image[ring] = int(image.mean())
        path = d / f"ringed_{k:04d}.png"
        imageio.write_image(path, image)
        frames.append(str(path))
    return d, frames


def _job(series, out, **kw):
    d, frames = series
    return ProcessJob(reference=str(d / "reference.png"), frames=frames, out=str(out),
                      geometry=str(d / "geometry.toml"), fft_effort="estimate", **kw)


@pytest.fixture(scope="module")
def serial(series, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "serial.h5"
    report = run_process(_job(series, out, workers=1))
    assert report.frames_written == N_FRAMES
    return _read(out)


def _read(path):
    with h5py.File(path) as f:
        data = {name: f[name][()] for name in ("height", "slope_x", "slope_y", "valid",
                                               "frame_index", "source", "pin_status", "frame_status",
                                               "frame_status_text")}
        data["attrs"] = dict(f.attrs)
    return data


def _assert_same(serial, other, complete=True):
    if complete:
        assert other["attrs"]["status"] == "complete"
    assert other["attrs"]["status"] == serial["attrs"]["status"]
    assert other["attrs"]["frames_done"] == N_FRAMES
    np.testing.assert_array_equal(other["frame_index"], serial["frame_index"])
    np.testing.assert_array_equal(other["source"], serial["source"])
    np.testing.assert_array_equal(other["valid"], serial["valid"])
    np.testing.assert_array_equal(other["frame_status"], serial["frame_status"])
    np.testing.assert_array_equal(other["frame_status_text"], serial["frame_status_text"])
    # /pin_status: where each frame was pinned and its series check against the frame before
    a, b = serial["pin_status"], other["pin_status"]
    for name in a.dtype.names:
        if name in ("region_motion_px", "frame_motion_px", "frame_motion_row_px", "frame_motion_col_px"):
            # (the last three over the whole frame, read at 0.03 px; a recording's mean at 0.2 px)
            # a median of the displacement (~1e-3 px here): the plans' rounding moves it by up to 1.9e-6
            # px between serial and parallel runs (measured 5 Dec 2026; 3.6e-6 in a loaded suite run),
            # which rtol 1e-3 of 1e-3 px did not hold. What it is read for is a move of 0.03 px
            # (pin.STILL_REGION_MAX_MOTION_PX) and a 2 pi slip moves it by a period: 1e-4 px.
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-4, equal_nan=True, err_msg=name)
        elif name == "frame_shift_share":
            # a share of about 1,000 samples within 0.05 px of that median: one sample's side of the bound
            # is 1e-3; read at 0.2 (pin.SHIFT_MIN_SHARE)
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=2.5e-3, equal_nan=True, err_msg=name)
        elif name in ("region_scale", "region_scale_reach_px", "region_scale_explained"):
            # the scale fitted to the pin samples (here ~1e-6, reach ~1e-3 px, explaining ~0.02 of their
            # noise): the plans' rounding moved the share by 2.5e-5 (7 Dec 2026); read at 0.1 px and 0.5
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-3, equal_nan=True, err_msg=name)
        elif a.dtype[name].kind == "f":
            np.testing.assert_allclose(b[name], a[name], rtol=1e-3, atol=1e-6, equal_nan=True, err_msg=name)
        else:
            np.testing.assert_array_equal(b[name], a[name], err_msg=name)
    peak = np.nanmax(np.abs(serial["height"]))
    for name in ("height", "slope_x", "slope_y"):
        np.testing.assert_array_equal(np.isnan(other[name]), np.isnan(serial[name]))
        scale = np.nanmax(np.abs(serial[name]))
        diff = np.nanmax(np.abs(other[name].astype(np.float64) - serial[name]))
        assert diff <= REL_TOL * scale, f"{name}: differs by {diff / scale:.2e} of its peak"
    assert peak > 1e-3  # micrometres: a real deformation, not an empty comparison


def test_series_needs_temporal_unwrapping(series, serial, tmp_path):
    """Precondition of the tests below: in space alone, frames 5-7 come out
    different (the check has something to catch)."""
    d, frames = series
    from processing import Geometry

    job = _job(series, tmp_path / "x.h5")
    reference = imageio.read_reference(job.reference)
    geometry = Geometry.from_toml(job.geometry)
    from processing import Reconstructor

    recon = Reconstructor(reference, geometry, grid="full", refine_method="fd")
    spec = parallel.ReconstructorSpec(key="t", reference=reference, geometry=geometry, options=recon.options,
                                      carriers=recon.carriers)
    # chunk 2 of 3-frame chunks: overlap frame 5, unwrapped in space; no check here
    chunk = parallel.plan_chunks(N_FRAMES, first=0, step=1, paths=frames, workers=2,
                                 frame_bytes=1, chunk_frames=3)[2]
    assert chunk.overlap == RING_FROM and (chunk.first, chunk.last) == (6, 8)
    unchecked = parallel.process_chunk(spec, chunk)
    peak = np.nanmax(np.abs(serial["height"]))
    wrong = [np.nanmax(np.abs(r.height - serial["height"][item.sequence_index])) / peak
             for item, (r, _) in unchecked.frames]
    assert max(wrong) > 0.01, wrong  # a slip: ~2 % of the peak
    # ... and the states at the join tell: frame 5 in space is not frame 5 in time
    serial_chunk = parallel.process_chunk(spec, parallel.plan_chunks(
        N_FRAMES, first=0, step=1, paths=frames, workers=2, frame_bytes=1, chunk_frames=6)[0])
    assert not unchecked.start.agrees_with(serial_chunk.end)


@pytest.mark.parametrize("shared_memory", [True, False], ids=["shared-memory", "pipes"])
def test_workers_give_serial_heights_and_redo_a_disagreeing_chunk(series, serial, tmp_path, caplog,
                                                                 monkeypatch, shared_memory):
    monkeypatch.setattr(parallel, "SHARED_MEMORY", shared_memory)
    out = tmp_path / "par.h5"
    with caplog.at_level("INFO", logger="app.batch.parallel"):
        report = run_process(_job(series, out, workers=2, chunk_frames=3))
    assert report.frames_written == N_FRAMES
    par = _read(out)
    _assert_same(serial, par)
    assert par["attrs"]["chunks"] == 4
    # exactly the chunk that starts from frame 5 was redone
    assert par["attrs"]["chunks_redone"] == 1
    assert any("chunk 2 (frames 6..8)" in r.getMessage() and "redone" in r.getMessage()
               for r in caplog.records)


def test_workers_from_the_cli_with_a_frame_selection(series, tmp_path):
    """--first/--step through the CLI; the selection and order are those of a serial run."""
    d, frames = series
    outs = {}
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}.h5"
        # as a user runs it: worker processes are spawned from `python -m app.cli`
        proc = subprocess.run([sys.executable, "-m", "app.cli", "process", str(d / "reference.png"),
                               *frames, "--geometry", str(d / "geometry.toml"), "--out", str(out),
                               "--first", "1", "--step", "2", "--workers", workers,
                               "--chunk-frames", "2", "--no-progress"],
                              cwd=root, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        outs[workers] = _read(out)
    np.testing.assert_array_equal(outs["2"]["frame_index"], [1, 3, 5, 7, 9, 11])
    np.testing.assert_array_equal(outs["1"]["frame_index"], outs["2"]["frame_index"])
    np.testing.assert_array_equal(outs["1"]["valid"], outs["2"]["valid"])
    scale = np.nanmax(np.abs(outs["1"]["height"]))
    assert np.nanmax(np.abs(outs["1"]["height"] - outs["2"]["height"])) <= REL_TOL * scale


def test_a_killed_worker_process_is_replaced(series, serial, tmp_path, caplog):
    """SIGKILL one of the pool's processes after the first frame is written
    (chunks still to compute): new workers take the chunks in flight and the
    output is still complete and serial's. A worker killed between a shared-memory
    block's creation and its registration with the resource tracker leaves the
    block's name in /dev/shm (what that moment leaves, an empty file named after the
    run, is made beside the kill here: the real moment is too short to aim at; one
    832 KB block stayed after a suite run, 6 Dec 2026): the run removes it when its
    workers have ended."""
    psutil = pytest.importorskip("psutil", reason="finding the worker processes needs psutil")
    killed = []
    half_made = f"/dev/shm/tdf{os.getpid()}_deadbeef00"

    def kill_a_worker(done, total):
        if killed or done < 1:
            return
        workers = worker_processes(psutil.Process())
        assert workers, "no worker process found"
        killed.append(workers[0].pid)
        os.kill(workers[0].pid, signal.SIGKILL)
        if os.path.isdir("/dev/shm"):
            os.close(os.open(half_made, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o600))

    import threading

    out = tmp_path / "killed.h5"
    before = set(threading.enumerate())
    with caplog.at_level("WARNING", logger="app.batch.parallel"):
        report = run_process(_job(series, out, workers=2, chunk_frames=2, on_progress=kill_a_worker))
    assert killed and report.frames_written == N_FRAMES
    assert not os.path.exists(half_made) and not _shm_blocks_of(os.getpid())
    assert any("worker process died" in r.getMessage() for r in caplog.records)
    _assert_same(serial, _read(out))
    # the broken pool's threads end: the program can exit (a feeder stuck on the
    # dead workers' pipe kept `tirdeflect process` from ever ending on CPython < 3.11.3)
    left = [t for t in set(threading.enumerate()) - before if not t.daemon]
    for t in left:
        t.join(timeout=10)
    assert not [t.name for t in left if t.is_alive()], "threads of the broken pool still running"


def test_ctrl_c_stops_workers_and_keeps_written_frames(series, tmp_path):
    """Ctrl-C at the terminal (SIGINT to the whole process group) during a
    --workers 2 run: exit status 130, the frames written are in the file,
    no worker process and no shared-memory block is left behind."""
    import re
    import subprocess
    import sys
    import threading

    psutil = pytest.importorskip("psutil", reason="finding the worker processes needs psutil")
    d, frames = series
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "out.h5"
    # OUT.h5 flushed every 20 ms instead of every 0.5 s: Ctrl-C must land mid-run, after
    # frames the log reported written (flushed)
    child = ("import sys, app.batch.writer; app.batch.writer.FLUSH_INTERVAL_S = 0.02; "
             "from app.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.Popen(
        [sys.executable, "-c", child, "--debug", "process", str(d / "reference.png"),
         *(frames * 4), "--geometry", str(d / "geometry.toml"), "--out", str(out),
         "--workers", "2", "--chunk-frames", "2", "--no-progress"],
        cwd=root, stderr=subprocess.PIPE, text=True, start_new_session=True,
        # as at a terminal (a test runner started in the background ignores SIGINT, and
        # its children would inherit that)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    done = 0
    workers = []

    def interrupt_at_the_third_frame(line):  # Ctrl-C at a terminal: the whole process group
        nonlocal done, workers
        if re.search(r"frame \d+ .* written", line):
            done += 1
            if done == 3:
                workers = [c.pid for c in worker_processes(psutil.Process(proc.pid))]
                os.killpg(proc.pid, signal.SIGINT)
                return True
        return False

    code, rest = stderr_until_signalled(proc, interrupt_at_the_third_frame)
    assert done == 3 and workers, "the run ended before three frames were written"
    assert code == 130, rest
    assert "Traceback" not in rest and rest.strip().endswith("tirdeflect: interrupted"), rest
    assert not out.exists()  # an interrupted run is not published under OUT ...
    kept = out.with_name("out.partial.h5")  # ... its frames are kept beside it
    with h5py.File(kept) as f:
        n = int(f.attrs["frames_done"])
        assert 3 <= n < 4 * N_FRAMES
        assert f.attrs["status"].startswith("interrupted")
        assert np.isfinite(f["height"][:n]).mean() > 0.8
    deadline = time.monotonic() + 10
    while any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
              for p in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
                   for p in workers), "worker processes outlived the run"
    left = _shm_blocks_of(proc.pid)
    assert not left, f"shared-memory blocks left behind: {left}"


def _shm_blocks_of(run_pid: int) -> list:
    """The shared-memory blocks the run with process ``run_pid`` holds (named by
    app.batch.shm_results.shm_name; other programs' blocks do not count)."""
    from app.batch.shm_results import shm_name

    prefix = shm_name(run_pid).rpartition("_")[0] + "_"
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(prefix)) if os.path.isdir("/dev/shm") else []


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="watches processes through /proc (Linux)")
def _cmdline_or_gone(process) -> str:
    """A psutil process's command line, "" when it already ended."""
    import psutil

    try:
        return " ".join(process.cmdline())
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return ""


def test_workers_end_when_the_run_is_killed(series, tmp_path):
    """SIGKILL (the OOM killer, kill -9) on a --workers 2 run: nothing can clean
    up in the run's process, so its workers must notice and end by themselves,
    and the shared-memory blocks they held are freed with them."""
    import re
    import subprocess
    import sys
    import threading

    psutil = pytest.importorskip("psutil", reason="finding the worker processes needs psutil")
    d, frames = series
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "--debug", "process", str(d / "reference.png"),
         *(frames * 4), "--geometry", str(d / "geometry.toml"), "--out", str(tmp_path / "out.h5"),
         "--workers", "2", "--chunk-frames", "2", "--no-progress"],
        cwd=root, stderr=subprocess.PIPE, text=True, start_new_session=True)
    watchdog = threading.Timer(120.0, proc.kill)
    watchdog.start()
    helpers, workers, cmdlines = [], [], {}
    try:
        for line in proc.stderr:
            if re.search(r"frame \d+ .* written", line):  # under way: chunks in flight
                run = psutil.Process(proc.pid)
                helpers = run.children(recursive=True)  # the fork server, its workers, the resource tracker
                workers = worker_processes(run)
                # read while the run is alive: once it is killed, a helper that ends
                # is a zombie until init reaps it, and a zombie has no command line
                cmdlines = {c.pid: _cmdline_or_gone(c) for c in helpers}
                proc.kill()
                break
        proc.wait(timeout=30)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    assert len(workers) == 2, list(cmdlines.values())
    # each worker checks twice a second whether the run is still there
    gone, alive = psutil.wait_procs(helpers, timeout=10)
    assert not alive, f"processes outlived the killed run by 10 s: {[cmdlines[p.pid] for p in alive]}"
    assert not _shm_blocks_of(proc.pid), "shared-memory blocks of the killed run left behind"


_BLOCK_MAKER = r"""
import dataclasses, multiprocessing as mp, os, sys, time
import numpy as np
from multiprocessing import resource_tracker
sys.path.insert(0, sys.argv[1])
from app.batch import parallel, shm_results
from app.worker_processes import parent_state

@dataclasses.dataclass
class Frame:
    maps: dict

def worker(run_pid, state, ready):
    parallel._init_worker(run_pid, state)
    frame = Frame({"height": np.zeros(64, np.float32)})
    ready.set()
    while True:  # a worker handing its maps over, as fast as it can
        shm_results.SharedFrame.put(frame)

if __name__ == "__main__":
    resource_tracker.ensure_running()
    ctx = mp.get_context("fork")
    ready = ctx.Event()
    w = ctx.Process(target=worker, args=(os.getpid(), parent_state(), ready), daemon=False)
    w.start()
    ready.wait(60)
    print(w.pid, resource_tracker._resource_tracker._pid, flush=True)
    time.sleep(60)
"""


def test_no_block_is_left_when_the_run_dies_while_a_worker_makes_one(tmp_path):
    """The run is SIGKILLed while its worker creates shared-memory blocks without pause: the worker
    ends (its watch thread sees the run gone) and the resource tracker frees every block it was told
    of. A block created but not yet registered when the watch thread ended the worker stayed in
    /dev/shm for good (on the first of three tries here, every time, before the watch thread waited for the block being made;
    208-832 KB blocks of dead runs were found after loaded suite runs)."""
    import subprocess
    import sys

    if not os.path.isdir("/dev/shm"):
        pytest.skip("no /dev/shm to look in")
    root = Path(__file__).resolve().parents[2]
    script = tmp_path / "block_maker.py"
    script.write_text(_BLOCK_MAKER)
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, str(script), str(root)], stdout=subprocess.PIPE, text=True)
        try:
            worker_pid, tracker_pid = (int(x) for x in proc.stdout.readline().split())
            time.sleep(0.3)  # let it make blocks for a while (the race needs no timing: any moment hits it)
            proc.kill()
            proc.wait(timeout=30)
            deadline = time.monotonic() + 60  # a hang detector: both end within a second normally
            while (parallel._process_alive(worker_pid) or parallel._process_alive(tracker_pid)) \
                    and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not parallel._process_alive(worker_pid), "the worker outlived the killed run by 60 s"
            assert not parallel._process_alive(tracker_pid), "the resource tracker outlived the worker by 60 s"
            left = _shm_blocks_of(proc.pid)
            for name in left:  # not to leave them to the next run of the suite
                os.unlink(os.path.join("/dev/shm", name))
            assert not left, f"{len(left)} shared-memory block(s) of the killed run left behind"
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.stdout.close()


def test_a_script_without_the_main_guard_is_told_what_to_do(series, tmp_path):
    """A physicist's script calls run_process(..., workers=2) at its top level: each
    worker process imports the script, which starts processes while it is being
    imported, and dies. The run ends with an error naming the script and the
    `if __name__ == "__main__":` idiom, nothing written; with the guard it works."""
    import subprocess
    import sys
    import textwrap

    d, frames = series
    root = Path(__file__).resolve().parents[2]
    call = (f"run_process(ProcessJob(reference={str(d / 'reference.png')!r}, frames={frames!r}, "
            f"geometry={str(d / 'geometry.toml')!r}, out=OUT, workers=2, fft_effort='estimate'))")
    head = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(root)!r})
        from app.batch import ProcessJob, run_process
        """)
    bare = tmp_path / "my_analysis.py"
    bare.write_text(head + f"OUT = {str(tmp_path / 'bare.h5')!r}\n" + call + "\n")
    guarded = tmp_path / "my_guarded_analysis.py"
    guarded.write_text(head + f"OUT = {str(tmp_path / 'guarded.h5')!r}\n"
                       + "if __name__ == '__main__':\n    " + call + "\n")
    run = subprocess.run([sys.executable, str(bare)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)
    assert run.returncode != 0
    assert "my_analysis.py calls run_process at its top level" in run.stderr
    assert 'if __name__ == "__main__":' in run.stderr
    assert not (tmp_path / "bare.h5").exists()
    run = subprocess.run([sys.executable, str(guarded)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    with h5py.File(tmp_path / "guarded.h5") as f:
        assert int(f.attrs["frames_done"]) == N_FRAMES


def test_bad_parallel_options_are_one_line_errors(series, tmp_path):
    import subprocess
    import sys

    d, frames = series
    root = Path(__file__).resolve().parents[2]
    base = [sys.executable, "-m", "app.cli", "process", str(d / "reference.png"), *frames[:4],
            "--geometry", str(d / "geometry.toml")]
    cases = [(["--workers", "2", "--dask", "local:2"], "exclude each other"),
             (["--dask", "local:zero"], "--dask 'local:zero'"),
             (["--workers", "0"], "must be >= 1"),
             (["--dask-send-frames"], "add --dask ADDRESS")]
    if distributed is not None:
        cases.append((["--dask", "nonsense"], "not a scheduler address"))
    from processing.gpu import cupy_or_reason

    if cupy_or_reason()[0] is None:
        cases.append((["--device", "cuda"], "device='cuda' is not available"))
    for k, (extra, expected) in enumerate(cases):
        out = tmp_path / f"bad{k}.h5"
        proc = subprocess.run(base + ["--out", str(out), *extra], cwd=root, capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert expected in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert not out.exists()  # nothing half-made left behind


def test_gui_export_of_a_long_recording_uses_every_core(series, tmp_path):
    """The GUI's export calls the batch engine without --workers: a recording of
    64 frames or more goes over all cores, with the heights of a serial run."""
    from app.gui.export import export_heights

    d, frames = series
    n = parallel.AUTO_PARALLEL_MIN_FRAMES
    order = [k % N_FRAMES for k in range(n)]  # the series again and again: jumps back included
    rec = tmp_path / "rec.h5"
    with h5py.File(rec, "w") as f:
        f["frames"] = np.stack([imageio.read_image(frames[k]) for k in order])
        f["reference"] = imageio.read_image(d / "reference.png")
        f["geometry_toml"] = (d / "geometry.toml").read_text()
    seen = []
    export_heights(str(rec), str(tmp_path / "export.h5"), progress=lambda done, total: seen.append(done))
    run_process(ProcessJob(reference=str(rec), frames=[str(rec)], out=str(tmp_path / "serial.h5"),
                           workers=1))
    with h5py.File(tmp_path / "export.h5") as a, h5py.File(tmp_path / "serial.h5") as b:
        assert a.attrs["parallel"].startswith(f"{parallel.available_cores()} processes") \
            or parallel.available_cores() == 1
        assert a.attrs["frames_done"] == n and seen[-1] == n
        np.testing.assert_array_equal(a["valid"][()], b["valid"][()])
        h, ref = a["height"][()], b["height"][()]
        assert np.nanmax(np.abs(h - ref)) <= REL_TOL * np.nanmax(np.abs(ref))


def test_device_cuda_batches_through_the_engine(series, serial, tmp_path, monkeypatch):
    """`--device cuda`'s path through the engine (batches, masked frames back on
    the CPU, order, output) with NumPy standing in for CuPy: the GPU chain is
    written against an array module, and this machine has no GPU (the same
    run on a GPU: benchmarks/gpu_check.py)."""
    from processing import gpu

    monkeypatch.setattr(gpu, "cupy_or_reason", lambda: (np, None))
    monkeypatch.setattr(parallel, "GPU_BATCH", 4)  # several batches of the 12 frames
    out = tmp_path / "gpu.h5"
    report = run_process(_job(series, out, device="cuda"))
    assert report.frames_written == N_FRAMES
    got = _read(out)
    assert got["attrs"]["device"] == "cuda"
    assert got["attrs"]["refine_method"] == "fd"  # image matching stays on the CPU: auto picks fd
    serial_fd = tmp_path / "serial_fd.h5"
    run_process(_job(series, serial_fd, workers=1, refine_method="fd"))
    _assert_same(_read(serial_fd), got)

    # a GPU with too little memory for 4 frames at once: CuPy raises OutOfMemoryError
    # (stood in for here by an exception of that name); the run halves its batches
    # and goes on from the same frames, with the same heights
    from processing.reconstruct import Reconstructor

    class OutOfMemoryError(Exception):
        pass

    tried = []
    batch = Reconstructor.batch

    def small_gpu(self, frames, *args, **kwargs):
        tried.append(len(frames))
        if len(frames) > 1:
            raise OutOfMemoryError("Out of memory allocating 1,073,741,824 bytes")
        return batch(self, frames, *args, **kwargs)

    monkeypatch.setattr(Reconstructor, "batch", small_gpu)
    out = tmp_path / "small_gpu.h5"
    report = run_process(_job(series, out, device="cuda"))
    assert report.frames_written == N_FRAMES
    assert tried[:3] == [4, 2, 1] and set(tried[3:]) == {1}, tried
    small = _read(out)
    assert small["attrs"]["gpu_batch"] == 1
    _assert_same(_read(serial_fd), small)

    # not even one frame fits: a one-line error that says what to do, not CuPy's traceback
    def no_gpu_memory(self, frames, *args, **kwargs):
        raise OutOfMemoryError("Out of memory allocating 8,388,608 bytes")

    monkeypatch.setattr(Reconstructor, "batch", no_gpu_memory)
    with pytest.raises(TirdeflectError, match="too little free memory for even one frame.*without --device cuda"):
        run_process(_job(series, tmp_path / "no_gpu.h5", device="cuda"))


@pytest.mark.parametrize("how", ["workers", "device-cuda"])
def test_invalid_frames_in_the_middle_match_serial(series, tmp_path, monkeypatch, how):
    """An unreadable file and a blank frame in the series: stored invalid with the
    serial run's status and reason, and the series starts again after each hole,
    whether the frames go over processes (chunks of 3) or in GPU batches."""
    d, frames = series
    frames = list(frames)
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png at all")
    blank = tmp_path / "blank.png"
    imageio.write_image(blank, np.full((SIZE, SIZE), 128, np.uint8))
    frames[3] = str(broken)
    frames[7] = str(blank)
    job = dict(reference=str(d / "reference.png"), frames=frames, geometry=str(d / "geometry.toml"),
               fft_effort="estimate")
    # the GPU chain refines by FD (auto picks fd with --device cuda): its serial twin too
    run_process(ProcessJob(out=str(tmp_path / "serial.h5"), workers=1,
                           refine_method="auto" if how == "workers" else "fd", **job))
    if how == "workers":
        run_process(ProcessJob(out=str(tmp_path / "other.h5"), workers=2, chunk_frames=3, **job))
    else:
        from processing import gpu

        monkeypatch.setattr(gpu, "cupy_or_reason", lambda: (np, None))  # NumPy standing in for CuPy
        monkeypatch.setattr(parallel, "GPU_BATCH", 4)
        run_process(ProcessJob(out=str(tmp_path / "other.h5"), device="cuda", **job))
    serial, other = _read(tmp_path / "serial.h5"), _read(tmp_path / "other.h5")
    assert (serial["frame_status"] != 0).sum() == 2  # the two holes, nothing else
    assert not serial["valid"][3].any() and not serial["valid"][7].any()
    _assert_same(serial, other, complete=False)


def test_chunks_fit_the_memory_budget():
    """Results of the chunks in flight fit the budget, by default an eighth of the
    memory available (at least 1 GiB): a 10,000-frame 1024^2 run on 16 workers."""
    frame_bytes = 1024 * 1024 * 13
    for budget in (parallel.MEMORY_BUDGET_BYTES, None):
        chunks = parallel.plan_chunks(10_000, first=0, step=1, paths=("rec.h5",), workers=16,
                                      frame_bytes=frame_bytes, memory_budget_bytes=budget)
        size = chunks[0].last - chunks[0].first + 1
        limit = budget or parallel.default_memory_budget_bytes()
        assert (16 + 2) * size * frame_bytes <= limit
        assert size >= limit // ((16 + 2) * frame_bytes) - 1, "chunks shorter than the budget allows"
        assert chunks[-1].last == 9_999 and all(c.overlap == c.first - 1 for c in chunks[1:])
    with open("/proc/meminfo") as fh:
        available = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("MemAvailable:"))
    assert parallel.default_memory_budget_bytes() == max(parallel.MEMORY_BUDGET_BYTES,
                                                         min(parallel.MEMORY_BUDGET_MAX_BYTES, available // 8)) \
        or abs(parallel.default_memory_budget_bytes() - available / 8) < 64 << 20  # memory moved meanwhile
    assert parallel.fft_threads(4, cores=16) == 4 and parallel.fft_threads(32, cores=16) == 1



def test_chunks_of_a_video_end_on_keyframes():
    """A worker starts decoding at the keyframe before its chunk's overlap frame:
    frames in between are decoded for nothing (47 ms each for FFV1 at 1024^2).
    With the keyframes known, chunks end on them where one lies in a chunk's
    second half: far fewer frames decoded for nothing; chunks stay within the
    memory budget's length and cover every selected frame once, in order."""
    keyframes = list(range(0, 1000, 12))

    def wasted(chunks):  # frames decoded only to reach the overlap frames
        return sum(c.overlap - max(k for k in keyframes if k <= c.overlap) for c in chunks[1:])

    for first, step in ((0, 1), (5, 1), (3, 2)):
        selected = (1000 - first + step - 1) // step
        kw = dict(first=first, step=step, paths=("a.avi",), workers=2, frame_bytes=13 << 20)
        plain = parallel.plan_chunks(selected, **kw)
        size = plain[0].last - plain[0].first + step
        chunks = parallel.plan_chunks(selected, keyframes=keyframes, **kw)
        frames = [f for c in chunks for f in range(c.first, c.last + 1, step)]
        assert frames == list(range(first, 1000, step))
        assert all(c.overlap == c.first - step for c in chunks[1:])
        lengths = [c.last - c.first + step for c in chunks]
        assert max(lengths) <= size and min(lengths[:-1]) >= size // 2
        if step == 1:
            assert wasted(chunks) <= 0.25 * wasted(plain), (wasted(chunks), wasted(plain))
    # an explicit --chunk-frames is taken as given
    chunks = parallel.plan_chunks(100, first=0, step=1, paths=("a.avi",), workers=2, frame_bytes=1,
                                  chunk_frames=10, keyframes=keyframes)
    assert [c.first for c in chunks] == list(range(0, 100, 10))


# ----------------------------------------------------------------- Dask

try:
    import distributed  # noqa: F401
except ImportError:
    distributed = None
_skip_without_dask = pytest.mark.skipif(distributed is None,
                                        reason="Dask tests need pip install 'tirdeflect[dask]' (dask[distributed])")


def needs_dask(test):
    """Skipped without Dask; one Dask cluster at a time on this PC (the ``dask_cluster`` mark,
    tests/conftest.py): a second scheduler's HTTP server moves off port 8787 with a warning and
    leaves the socket it could not bind unclosed."""
    return pytest.mark.dask_cluster(_skip_without_dask(test))


@needs_dask
@pytest.mark.parametrize("send_frames", [False, True], ids=["shared-files", "frames-sent"])
def test_dask_local_gives_serial_heights(series, serial, tmp_path, send_frames):
    out = tmp_path / "dask.h5"
    report = run_process(_job(series, out, dask="local:2", chunk_frames=3, send_frames=send_frames))
    assert report.frames_written == N_FRAMES
    par = _read(out)
    _assert_same(serial, par)
    assert par["attrs"]["chunks_redone"] == 1


@needs_dask
def test_dask_local_from_the_console_says_only_what_the_run_says(series, serial, tmp_path):
    """`tirdeflect process ... --dask local:2` as typed: the same heights as the serial run, and on the
    terminal only tirdeflect's own lines. Dask's loggers are set to INFO by Dask itself and printed
    through the CLI's handler: 34 lines of cluster start and stop on every run (a by-hand trial,
    7 Dec 2026)."""
    import subprocess
    import sys

    d, frames = series
    out = tmp_path / "console.h5"
    proc = subprocess.run([sys.executable, "-m", "app.cli", "process", str(d / "reference.png"), *frames,
                           "--geometry", str(d / "geometry.toml"), "--out", str(out), "--fft-effort", "estimate",
                           "--dask", "local:2", "--chunk-frames", "3"],
                          cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert not [ln for ln in proc.stderr.splitlines() if ": INFO:" in ln or ": DEBUG:" in ln], proc.stderr
    _assert_same(serial, _read(out))


@needs_dask
def test_dask_reruns_the_chunk_of_a_killed_worker(series, serial, tmp_path):
    """A worker process is SIGKILLed while it computes a chunk: Dask's nanny
    restarts it, the scheduler gives the chunk to a worker again, and the
    output is complete and identical to the serial run."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        pids = client.run(os.getpid)  # {worker address: pid}
        killed = {}

        def kill_a_busy_worker(done, total):
            if killed or done < 1:
                return
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                for address, keys in client.processing().items():
                    busy = [str(k) for k in keys if str(k).startswith("tirdeflect-")]
                    if busy:
                        killed.update(pid=pids[address], keys=busy)
                        os.kill(pids[address], signal.SIGKILL)
                        return
                time.sleep(0.005)
            raise AssertionError("no worker was computing a chunk within 30 s")

        out = tmp_path / "killed.h5"
        report = run_process(_job(series, out, dask=cluster.scheduler_address, chunk_frames=2,
                                  on_progress=kill_a_busy_worker))
        assert killed, "the run ended before a worker could be killed"
        assert report.frames_written == N_FRAMES
        _assert_same(serial, _read(out))
        # the killed process is gone, the nanny started a new one
        client.wait_for_workers(2, timeout=60)
        assert killed["pid"] not in client.run(os.getpid).values()
        # the scheduler lost the killed chunk with its worker and computed it again
        for key in killed["keys"]:
            moves = [(t[2], t[3]) for t in client.story(key) if t[0] == "scheduler" and t[1] == key]
            # lost with its worker while computing, or just after it finished (the result
            # died with the worker before the client fetched it): either way released again
            lost = [i for i, (start, finish) in enumerate(moves)
                    if start in ("processing", "memory") and finish in ("released", "waiting")]
            assert lost, f"chunk {key} was never lost with its worker: {moves}"
            assert ("processing", "memory") in moves[lost[0] + 1:], f"chunk {key} was not computed again: {moves}"


def _page_faults_of_big_arrays(count: int = 20) -> int:
    """Minor page faults of allocating and freeing an 8 MB array ``count`` times (this process)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(count):
        a = np.ones(1 << 20)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def _faults_before_and_after_reuse() -> tuple:
    # numpy asks for transparent huge pages on large arrays: whether the kernel has
    # some free decides between 4 and 2048 faults per fresh 8 MB mapping; small pages
    # here, so that the count is what it measures
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # numpy 1
        from numpy.core.multiarray import _set_madvise_hugepage
    _set_madvise_hugepage(False)
    _page_faults_of_big_arrays(2)
    before = _page_faults_of_big_arrays()
    switched = parallel.reuse_freed_memory()
    _page_faults_of_big_arrays(2)
    return before, switched, _page_faults_of_big_arrays()


@needs_dask
@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="glibc's allocator (Linux)")
def test_dask_workers_share_the_cores_and_reuse_freed_memory():
    """In a real LocalCluster of 2 one-thread worker processes:

    - each worker counts the 2 tasks that run at once on its machine (from the
      scheduler's list of workers), so its FFT threads are cores // 2, not
      every core in every worker (`dask worker --nworkers 16 --nthreads 1`
      would otherwise run 16 x 16 threads on 16 cores);
    - the nanny starts workers with MALLOC_TRIM_THRESHOLD_ set, which makes every
      freed map go back to the system and every new one come fresh from the
      kernel, page by page (a 1024^2 frame 3.4x slower): freshly faulted pages
      for each 8 MB array before reuse_freed_memory() (which _reconstructor
      calls), nearly none after."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        per_host = parallel._dask_tasks_per_host(client)
        on_machine = [client.submit(parallel._tasks_on_this_machine, per_host, workers=[a], pure=False).result()
                      for a in client.scheduler_info()["workers"]]
        envs = client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_")
        faults = client.run(_faults_before_and_after_reuse)
    assert len(per_host) == 1 and per_host[0][1] == 2, per_host
    assert on_machine == [2, 2]
    assert parallel.fft_threads(on_machine[0], cores=16) == 8
    assert all(v is not None for v in envs.values()), \
        "this Dask's nanny no longer sets MALLOC_TRIM_THRESHOLD_: reuse_freed_memory may go"
    for before, switched, after in faults.values():
        assert switched
        # 20 arrays of 2048 pages: thousands of faults when each is a fresh mapping;
        # reused heap memory faults no page at all
        assert before > 2000, f"{before} page faults before the switch: the nanny's setting had no effect"
        assert after < before / 20, f"{after} page faults after the switch (before: {before})"
