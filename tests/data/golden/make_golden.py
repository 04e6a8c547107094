"""Make tests/data/golden/reconstruct_golden.npz: every Result field of the
Reconstructor on ray-traced 128^2 cases, written by the code as it was before
the issue-19 split of processing/reconstruct.py into a plan and stages.

tests/processing/test_golden_refactor.py runs the same cases through the code
as it is now and compares field by field (bit-identical, or within 1e-6 of the
field's RMS).  Both sides run under :func:`fixed_fft_plans` with
:data:`FIXED_FFT`, so that the FFT plans, the one thing that otherwise varies
between runs of the same code on one machine, are the same.

The file was written by the code before the split (commit 3173c53) with this
file copied into a throwaway worktree of it:

    git worktree add /tmp/golden_old 3173c53
    cp tests/data/golden/make_golden.py /tmp/golden_old/tests/data/golden/
    cd /tmp/golden_old && PYTHONPATH=$PWD python tests/data/golden/make_golden.py OUT.npz

Regenerate ONLY when a change of the numbers is intended (and say why in the
commit): ``PYTHONPATH=$PWD python tests/data/golden/make_golden.py``, or one
case alone, the others kept as written: ``... make_golden.py --case NAME``.

Rewritten since: ``dots_full`` (2026-12-03), when PIV's vectors began to be
checked against the images (:func:`processing.piv.window_correlation`): of
its 961 vectors (8 px windows on a 128^2 frame) 48 correlated below 0.5 and
were off by 2.8-4.8 px RMS (the rest by 0.43 px); they are invalid now.
``series_full_fd`` and ``ifft_full`` (2026-12-05), when FD's full grid
began to measure its phase, and its refinement its correction, on the frame
continued beyond its border (:mod:`processing.continuation`) and the
reference it warps was band-limited continued too: against the ray-traced
truth the displacement of their three frames came out 12.7 / 45.7 / 17.1 %
off before and 7.9 / 24.3 / 10.8 % now (the ifft case's heights 6.8 -> 2.9 %).
Image matching's start keeps the taper: its cases are as written.
``series_full_image`` and ``masked_full`` (2026-12-05, later), when image
matching began to leave out the pixels whose warp samples beyond the
reference's border (OpenCV's mirror image there) and the outer two pixels of
each side (``dic.BORDER_PX``): against the truth their displacement came out
2.44 / 2.48 / 18.56 % off before and 2.13 / 2.00 / 17.25 % now; heights over
the interior 0.21 / 0.27 / 8.50 -> 0.18 / 0.25 / 8.43 %, over the whole frame
0.91 / 0.93 / 9.82 -> 0.92 / 0.95 / 9.99 %. ``series_full_image`` again the
same day (heights within 1.1e-6 of their RMS) when a sample's weight began to
fall over one pixel beyond the border instead of at it.  Both again the same
day, later, when checkerboards' image matching began to keep its first
Gauss-Newton step's matrix (``chain_image.MATRIX_ONCE``): displacement against
the truth 2.13 / 2.00 / 17.25 -> 2.12 / 1.99 / 17.48 %, heights over the interior
0.18 / 0.25 / 8.43 -> 0.18 / 0.25 / 8.15 %, over the whole frame 0.92 / 0.95 /
9.99 -> 0.92 / 0.95 / 9.59 %.  ``masked_full`` once more, when image matching on
checkerboards began to take ``dic.MASKED_CG_ITERATIONS`` (10) conjugate-gradient
iterations a step on frames with masked pixels: displacement 17.48 -> 18.22 %,
heights over the interior 8.15 -> 6.95 %, over the whole frame 9.59 -> 7.41 %.
``masked_full``, ``ifft_full`` and ``series_full_fd`` the same day, when FD's
bias removal began to leave the samples within ``refine.MASK_REACH_SAMPLES`` (2)
of a masked one as measured: displacement against the truth 18.22 / 10.76 /
7.88 / 24.32 -> 18.24 / 9.97 / 7.53 / 30.60 % (series_full_fd's two frames
last), heights over the whole frame 7.41 / 4.23 / 3.66 / 12.24 -> 6.61 / 4.09 /
3.51 / 12.91 %, over the interior 6.95 / 2.88 / 3.73 / 14.30 -> 6.36 / 3.08 /
3.68 / 14.66 % (the deeper bump, 45 % of its 128^2 frame masked by ray
crossings, is the one worse; refine.MASK_REACH_SAMPLES says why it is kept).
``masked_full`` (2026-12-06), when image matching on frames with masked pixels
began to take each Gauss-Newton step's own matrix (``chain_image.MATRIX_ONCE``:
beside a hole the first step's led the later ones astray): heights over the
interior 6.36 -> 2.55 %, over the whole frame 6.61 -> 2.59 %.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import numpy as np
import pyfftw

from processing import forward as F
from processing.geometry import Geometry
from processing.reconstruct import Reconstructor

N = 128
OUT = Path(__file__).with_name("reconstruct_golden.npz")
G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
BOARD = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)  # 20 x 11.5 px periods
DOTS = F.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=1)
FSSS = Geometry(setup="fsss", pixel_mm=0.2, fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)),
                n_water=1.34)
BUMP = F.GaussianBump(amplitude_mm=0.003, sigma_mm=2.5)
WAVES = F.WaveField.random(4, amplitude_rms_mm=0.0004, wavelength_range_mm=(8.0, 16.0), seed=3)


def _frames(surfaces, geometry, pattern, *, fsss=False, seed=0):
    rng = np.random.default_rng(seed)
    render = F.render_fsss if fsss else F.render_tir
    ref, _ = render(F.FlatSurface(), geometry, (N, N), pattern, supersample=2)
    imgs = [render(s, geometry, (N, N), pattern, supersample=2)[0] for s in surfaces]
    q = [F.quantize(a, bits=8, noise_rms=0.5, rng=rng) for a in [ref] + imgs]
    return q[0], q[1:]


def cases():
    """``{name: (reference, frames, geometry, options)}``, each run as one series."""
    ref, (bump, waves) = _frames([BUMP, WAVES], G55, BOARD)
    spike = F.SumSurface([BUMP, F.GaussianBump(amplitude_mm=0.01, sigma_mm=0.8, x0_mm=2.0, y0_mm=-1.5)])
    _, (masked,) = _frames([spike], G55, BOARD)
    masked = masked.copy()
    masked[90:110, 10:40] = masked.mean()  # a blank part (the pattern not seen)
    dref, (dimg,) = _frames([BUMP], G55, DOTS)
    fref, (fimg,) = _frames([F.GaussianBump(amplitude_mm=0.01, sigma_mm=5.0)], FSSS, BOARD, fsss=True)
    deeper = F.GaussianBump(amplitude_mm=0.009, sigma_mm=2.5)
    _, (b2, w2) = _frames([deeper, F.SumSurface([WAVES, F.GaussianBump(amplitude_mm=0.001, sigma_mm=3.0)])],
                          G55, BOARD)
    return {
        "series_two_frames": (ref, [bump, b2], G55, dict(grid="decimated")),
        "series_all_valid": (ref, [waves, w2], G55, dict(grid="decimated")),
        "series_full_image": (ref, [waves, w2], G55, {}),
        "series_full_fd": (ref, [bump, b2], G55, dict(refine_method="fd")),
        "ifft_full": (ref, [masked], G55, dict(refine_method="fd", full_method="ifft")),
        # PIV's full grid (written before dots' image matching, issue 22, which refine_method="fd" leaves out)
        "dots_full": (dref, [dimg], G55, dict(pattern="dots", window_px=8, refine_method="fd")),
        "fsss_decimated": (fref, [fimg], FSSS, dict(grid="decimated")),
        "masked_full": (ref, [masked], G55, {}),
        "masked_decimated": (ref, [masked], G55, dict(grid="decimated")),
    }


#: The FFT setting of both sides, through the public options: FFTW's estimate
#: planner (no timing: the plan is a function of the problem alone) on one
#: thread.  FFTW_MEASURE (the app's) picks among algorithms by timing them, so
#: it can choose another one in another run, and threads split the work.
FIXED_FFT = dict(planner_effort="FFTW_ESTIMATE", threads=1)


@contextlib.contextmanager
def fixed_fft_plans():
    """Run with FFTW's wisdom set aside (restored afterwards).

    FFTW uses the wisdom a process has accumulated for a problem (from any
    plan at least as rigorous, e.g. an earlier FFTW_MEASURE plan of the same
    shape, or wisdom imported from the app's cache) even for an FFTW_ESTIMATE
    plan: in a run of the whole suite the same code then takes other plans
    whose float32 rounding differs (up to 2.6e-5 of a field's RMS was seen).
    Without wisdom, FFTW_ESTIMATE plans the same transforms every time.
    """
    saved = pyfftw.export_wisdom()
    pyfftw.forget_wisdom()
    try:
        yield
    finally:
        pyfftw.forget_wisdom()
        pyfftw.import_wisdom(saved)


#: Frames run (their series memory feeds the next) but not stored: keeps the file < 2 MB.
NOT_STORED = {"series_full_fd/0"}


def result_fields(res) -> dict:
    """Every Result field as arrays (scalars and text as 0-d arrays)."""
    out = {}
    for name in ("height", "valid", "slope_x", "slope_y", "displacement", "amplitude", "x_mm", "y_mm",
                 "rows_px", "cols_px", "phase"):
        out[name] = np.asarray(getattr(res, name))
    out["grid"] = np.array(res.grid)
    out["valid_fraction"] = np.array(res.valid_fraction)
    out["note"] = np.array(res.note)
    pin = res.pin
    out["pin"] = np.array(repr(None) if pin is None else repr(
        {k: (v if not isinstance(v, np.ndarray) else v.tolist()) for k, v in vars(pin).items()}))
    out["series"] = np.array(repr(res.series))
    out["carriers"] = np.array(repr(None) if res.carriers is None else repr(np.asarray(res.carriers.freq).tolist()))
    return out


def run_all() -> dict:
    """``{"case/frame/field": array}`` of the code as it is, under :func:`fixed_fft_plans`."""
    out = {}
    all_cases = cases()
    with fixed_fft_plans():
        for name, (ref, frames, geometry, opts) in all_cases.items():
            out.update(_run_case(name, ref, frames, geometry, opts))
    return out


def _run_case(name, ref, frames, geometry, opts) -> dict:
    """One case's frames as one series, its fields keyed ``"case/frame/field"``."""
    out = {}
    rec = Reconstructor(ref, geometry, **opts, **FIXED_FFT)
    for i, frame in enumerate(frames):
        res = rec(frame)
        if f"{name}/{i}" in NOT_STORED:
            continue
        for field, value in result_fields(res).items():
            out[f"{name}/{i}/{field}"] = value
    return out


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--case"]:  # one case rewritten, every other field kept as the file has it
        name = args[1]
        path = Path(args[2]) if len(args) > 2 else OUT
        with np.load(path) as old:
            data = {k: old[k] for k in old.files if not k.startswith(name + "/")}
        ref, frames, geometry, opts = cases()[name]
        with fixed_fft_plans():
            data.update(_run_case(name, ref, frames, geometry, opts))
    else:
        path = Path(args[0]) if args else OUT
        data = run_all()
    np.savez_compressed(path, **data)
    print(f"{path}: {len(data)} arrays, {path.stat().st_size / 1e6:.2f} MB")
