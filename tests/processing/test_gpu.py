"""The batched GPU chain (processing/gpu.py) against the CPU Reconstructor.

The chain is written against an array module: with NumPy it runs here, on
the CPU, and must give the CPU path's heights (the issue's bar: within 1e-3
of the RMS height; measured ~4e-6). With CuPy and a GPU the same comparison
runs on the device; without them those tests skip and say why.
"""

import dataclasses

import cv2
import numpy as np
import pytest

from processing import forward as F
from processing.errors import TirdeflectError
from processing.geometry import Geometry
from processing.gpu import BatchChain, cupy_or_reason, lanczos_matrix, ran_on_gpu
from processing.reconstruct import Reconstructor

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
BOARD = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
N = 256
TOL = 1e-3  # of the RMS height (issue 9)


@pytest.fixture(scope="module")
def series():
    """A dimple deepening over 8 frames: carrier phase beyond pi from frame 4
    (temporal unwrapping), rays crossing on its flank in frames 6-7 (masked)."""
    ref, _ = F.render_tir(F.FlatSurface(), G55, (N, N), BOARD, supersample=1)
    frames = []
    for k in range(8):
        img, _ = F.render_tir(F.Dimple((k + 1) * 0.0006, 3.2), G55, (N, N), BOARD, supersample=1)
        frames.append(F.quantize(img, bits=8, noise_rms=0.0, rng=np.random.default_rng(k)))
    return F.quantize(ref, bits=8, noise_rms=0.0, rng=np.random.default_rng(99)), frames


def _compare(cpu_results, other_results):
    worst = 0.0
    for a, b in zip(cpu_results, other_results, strict=True):
        np.testing.assert_array_equal(a.valid, b.valid)
        # where the height was pinned, and the series check against the frame before
        # (the pattern's motion on the pin samples: float32 medians on the device, to 1e-4 px)
        # and over the whole frame, with its share that moved alike: the same; float32 medians and shares
        # on the device, to 1e-4 px and 1e-3)
        motions = ("region_motion_px", "frame_motion_px", "frame_shift_share", "frame_motion_row_px",
                   "frame_motion_col_px", "shift_effect_um", "shift_level_um", "region_scale",
                   "region_scale_reach_px", "region_scale_explained")
        assert (dataclasses.replace(a.pin, **dict.fromkeys(motions, 0.0))
                == dataclasses.replace(b.pin, **dict.fromkeys(motions, 0.0)))
        assert a.pin.region_motion_px == pytest.approx(b.pin.region_motion_px, abs=1e-4)
        assert a.pin.frame_motion_px == pytest.approx(b.pin.frame_motion_px, abs=1e-4)
        assert a.pin.frame_motion_row_px == pytest.approx(b.pin.frame_motion_row_px, abs=1e-4)
        assert a.pin.frame_motion_col_px == pytest.approx(b.pin.frame_motion_col_px, abs=1e-4)
        assert a.pin.frame_shift_share == pytest.approx(b.pin.frame_shift_share, abs=2.5e-3)  # (one of ~1,000 samples: 1e-3)
        assert a.pin.shifted == b.pin.shifted
        # the image's scale change fitted on the pin samples (float32 displacements on the device)
        assert a.pin.region_scale == pytest.approx(b.pin.region_scale, abs=1e-7)  # 0.00001 % of scale
        assert a.pin.region_scale_explained == pytest.approx(b.pin.region_scale_explained, abs=1e-3)
        assert a.pin.scaled == b.pin.scaled
        assert (a.series is None) == (b.series is None)
        if a.series is not None:
            assert (a.series.flagged, a.series.compared_samples) == (b.series.flagged, b.series.compared_samples)
            assert a.series.unwrap_slip_fraction == pytest.approx(b.series.unwrap_slip_fraction, abs=1e-6)
        rms = np.sqrt(np.nanmean(a.height.astype(np.float64) ** 2))
        worst = max(worst, float(np.nanmax(np.abs(a.height - b.height))) / rms)
        for name in ("slope_x", "slope_y"):
            s = getattr(a, name)
            scale = np.sqrt(np.nanmean(s.astype(np.float64) ** 2))
            assert np.nanmax(np.abs(s - getattr(b, name))) <= TOL * scale, name
    assert worst <= TOL, f"heights differ by {worst:.2e} of the RMS height"
    return worst


def test_lanczos_matrices_are_cv2_resize():
    rng = np.random.default_rng(0)
    f = rng.standard_normal((43, 37)).astype(np.float32)
    expected = cv2.resize(f, (256, 200), interpolation=cv2.INTER_LANCZOS4)
    got = lanczos_matrix(200, 43) @ f @ lanczos_matrix(256, 37).T
    assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()


@pytest.mark.parametrize("grid", ["decimated", "full"])
def test_chain_on_numpy_gives_the_cpu_heights(series, grid):
    ref, frames = series
    cpu = Reconstructor(ref, G55, refine_method="fd")  # the GPU chain is FD's
    expected = [cpu(f, grid=grid) for f in frames]
    assert expected[5].valid.all() and float(np.abs(expected[5].phase).max()) > np.pi
    assert not expected[-1].valid.all()  # the last frames are masked: the CPU's part
    chained = Reconstructor(ref, G55, refine_method="fd")
    chain = BatchChain(chained, np)
    assert chain.reason is None
    got = chain(frames[:3], grid) + chain(frames[3:], grid)  # two batches: the series goes on
    _compare(expected, got)
    on_chain = [k for k, r in enumerate(got) if ran_on_gpu(r)]
    assert on_chain == [0, 1, 2, 3, 4, 5], on_chain  # every all-valid frame
    assert not any(ran_on_gpu(got[k]) for k in range(len(got)) if not expected[k].valid.all())
    # the live path: one frame per call, the first one unwrapped in space
    single = BatchChain(Reconstructor(ref, G55, refine_method="fd"), np)
    _compare(expected, [single([f], grid)[0] for f in frames])


def test_chain_without_unwrapping_leaves_masked_frames_to_the_cpu(series):
    """unwrap=False (`--no-unwrap`): a frame where part of the pattern is faint (a
    fifth of its contrast: below min_amplitude, masked by the CPU's chain) while its
    phase stays smooth must go to the CPU from the batch too, not come back valid
    everywhere."""
    ref, frames = series
    blanked = [f.copy() for f in frames[:4]]
    yy, xx = np.mgrid[:N, :N]
    faint = np.hypot(yy - 150, xx - 100) < 30
    mean = float(frames[2].mean())
    blanked[2][faint] = np.round(mean + 0.2 * (frames[2][faint] - mean)).astype(frames[2].dtype)
    expected = [Reconstructor(ref, G55, unwrap=False, refine_method="fd")(f, grid="decimated") for f in blanked]
    assert [r.valid.all() for r in expected] == [True, True, False, True]
    got = BatchChain(Reconstructor(ref, G55, unwrap=False, refine_method="fd"), np)(blanked, "decimated")
    for k in range(4):
        np.testing.assert_array_equal(got[k].valid, expected[k].valid, err_msg=f"frame {k}")
    assert ran_on_gpu(got[1]) and not ran_on_gpu(got[2]), "the masked frame stayed on the batch"


def test_heights_that_need_the_second_order_go_to_the_cpu(series):
    """On the full grid the CPU solves the heights of a deep dimple again to second order
    (processing/second_order.py); the batch hands such frames to the CPU instead of returning
    first-order heights (0.2 % off): heights equal to the CPU's. A shallow dimple's batch stays on it."""
    ref, frames = series
    deep, _ = F.render_tir(F.Dimple(0.015, 9.0), G55, (N, N), BOARD, supersample=1)
    deep = F.quantize(deep, bits=8, noise_rms=0.0, rng=np.random.default_rng(7))
    for batch, on_chain in (([frames[0], frames[1]], [True, True]), ([deep, deep], [False, False])):
        cpu = Reconstructor(ref, G55, refine_method="fd")
        expected = [cpu(f, grid="full") for f in batch]
        assert [("second_order" in r.timings_ms) for r in expected] == [not c for c in on_chain]
        got = BatchChain(Reconstructor(ref, G55, refine_method="fd"), np)(batch, "full")
        _compare(expected, got)
        assert [ran_on_gpu(r) for r in got] == on_chain


def test_chain_takes_only_what_it_reproduces(series):
    """The chain resizes with the spline (default) or Lanczos only: another full-grid
    interpolation (4 % of the RMS height apart) goes through the CPU, and the Reconstructor says why;
    so do frames whose turn since the reference is to be taken out."""
    ref, _ = series
    for interpolation in ("cubic", "linear"):
        chain = BatchChain(Reconstructor(ref, G55, full_interpolation=interpolation, refine_method="fd"), np)
        assert chain.reason is not None and "lanczos" in chain.reason
    assert BatchChain(Reconstructor(ref, G55, refine_method="fd"), np).reason is None
    assert BatchChain(Reconstructor(ref, G55, refine_method="fd", full_interpolation="lanczos"), np).reason is None
    assert Reconstructor(ref, G55).gpu_fallback is None  # device="cpu": nothing falls back
    # a turn of camera or board taken out (processing.turn): the chain does not measure it, the CPU does
    for removal in ("camera", "board"):
        chain = BatchChain(Reconstructor(ref, G55, refine_method="fd", turn_removal=removal), np)
        assert chain.reason is not None and "turn_removal" in chain.reason


def test_device_cuda_without_a_gpu_says_why(series):
    cupy, why = cupy_or_reason()
    if cupy is not None:
        pytest.skip("a GPU is present: the error path cannot be shown")
    ref, _ = series
    with pytest.raises(TirdeflectError, match="device='cuda' is not available"):
        Reconstructor(ref, G55, device="cuda")


@pytest.mark.parametrize("grid", ["decimated", "full"])
def test_device_cuda_gives_the_cpu_heights(series, grid):
    cupy, why = cupy_or_reason()
    if cupy is None:
        pytest.skip(f"no GPU for device='cuda': {why}")
    ref, frames = series
    cpu = Reconstructor(ref, G55, refine_method="fd")  # the GPU chain is FD's
    expected = [cpu(f, grid=grid) for f in frames]
    gpu = Reconstructor(ref, G55, device="cuda")
    _compare(expected, gpu.batch(frames[:3], grid=grid) + gpu.batch(frames[3:], grid=grid))


def test_the_prepared_gpu_check_runs_through(tmp_path):
    """benchmarks/gpu_check.py is the one script a session lent a GPU runs, with 15
    minutes for it all: its whole flow (correctness at 256^2 against the CPU, then the
    speed part) runs here on NumPy named cupy, so that a slip in the script cannot waste
    that session. The heights must agree as the chain's own tests require (NumPy:
    ~4e-6 of the RMS); the speeds printed are NumPy's and only have to be printed."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent / "numpy_cupy"))
    r = subprocess.run([sys.executable, str(root / "benchmarks" / "gpu_check.py"), "--size", "256",
                        "--batch", "4", "--rounds", "2"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert "NumPy stand-in" in r.stdout, r.stdout + r.stderr
    lines = [line for line in r.stdout.splitlines() if "max|dh|/rms" in line]
    assert len(lines) == 6 and all(line.endswith("PASS") for line in lines), r.stdout
    for grid in ("full", "decimated"):
        assert f"batch {grid}" in r.stdout and "frames/s" in r.stdout
    assert "live single frame (decimated): median" in r.stdout
    # the correctness lines all passed, so exit 1 can only be NumPy missing the GPU's goals
    assert r.returncode in (0, 1) and "Traceback" not in r.stderr, r.stdout + r.stderr
    assert "gpu_check: all PASS" in r.stdout or "gpu_check: some FAIL" in r.stdout


def test_the_gpu_profile_runs_through(tmp_path):
    """benchmarks/gpu_profile.py (the stage times docs/processing.md quotes) runs on a
    lent GPU in the same call as gpu_check: its flow runs here on NumPy named cupy. Every
    stage of the chain must be timed (a renamed stage would silently drop out), and the
    stages must account for the batch's wall time (they are the whole batch)."""
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent / "numpy_cupy"))
    r = subprocess.run([sys.executable, str(root / "benchmarks" / "gpu_profile.py"), "--size", "256",
                        "--batch", "4", "--rounds", "1"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    rows = [line for line in r.stdout.splitlines() if "ms/frame wall" in line]
    assert len(rows) == 4, r.stdout
    for line in rows:
        wall, stages = map(float, re.search(r"([\d.]+) ms/frame wall \(stages ([\d.]+)\)", line).groups())
        # loose: a loaded machine preempts between stages, for a scheduler tick or more (up to 4 ms):
        # on the decimated rows' 1-2 ms a frame one preemption is half the wall time (it failed so
        # once under pytest -n 2), so there the names below are the check
        assert stages <= 1.05 * wall and (stages >= 0.5 * wall or wall - stages < 5.0), line
        for stage in ("demodulate", "unwrap", "height", "results") + (("warp_smooth",) if "full" in line else ()):
            assert f" {stage} " in line, line
    assert "live single frame:" in r.stdout


def test_the_gpu_live_check_runs_through(tmp_path):
    """benchmarks/gpu_live_check.py (the window's live path on a GPU: the worker process
    rebuilding a device="cuda" reconstructor) runs on NumPy named cupy here, child process
    included. On NumPy the app's scene (masked samples in every frame) goes to the CPU and
    the travelling waves stay on the chain; both must match the CPU."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parent / "numpy_cupy"))
    r = subprocess.run([sys.executable, str(root / "benchmarks" / "gpu_live_check.py"), "--size", "256",
                        "--frames", "12"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "gpu_live_check: PASS" in r.stdout, r.stdout + r.stderr
    assert "0/12 frames on the GPU" in r.stdout and "12/12 frames on the GPU" in r.stdout, r.stdout
