"""Every Result field as before the split of processing/reconstruct.py (issue 19).

tests/data/golden/reconstruct_golden.npz was written by
tests/data/golden/make_golden.py with the code before the Reconstructor became
a facade over a plan and stage modules; the same ray-traced cases (checkerboard
full grid with the default image refinement and with FD, decimated grid, series
of two frames with temporal unwrapping and the series check, full-size inverse
FFTs, random dots, FS-SS, a frame with a blank part and ray crossings) run
through the code as it is now must give the same numbers: bit-identical, or,
where an FFT plan differs, within 1e-4 of the field's RMS.  Plans do differ
between runs on one machine (FFTW's wisdom and thread count, OpenCV's thread
split): a fresh-clone run of the whole suite put the float32 fields up to
2.6e-5 of their RMS from the file written in a run of these tests alone
(issue 19 asked for 1e-6, which float32 through another plan cannot hold).
A refactor's real mistakes (a lost term, stages out of order, a 2 pi slip)
are 1e-3 and more.  Booleans, shapes and text (grid, note, pin, series) must
be equal.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
#: float32 through other FFT plans: up to 2.6e-5 of a field's RMS seen (see above)
TOLERANCE_OF_RMS = 1e-4


def _maker():
    spec = importlib.util.spec_from_file_location("make_golden", GOLDEN / "make_golden.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def now_and_then():
    with np.load(GOLDEN / "reconstruct_golden.npz") as f:
        then = {k: f[k] for k in f.files}
    return _maker().run_all(), then


def _differences(now, then):
    bad, inexact = [], 0
    for key in sorted(then):
        old = then[key]
        if key not in now:
            bad.append(f"{key}: missing")
            continue
        new = now[key]
        if new.shape != old.shape or new.dtype != old.dtype:
            bad.append(f"{key}: {new.dtype}{new.shape} != {old.dtype}{old.shape}")
        elif np.array_equal(new, old, equal_nan=old.dtype.kind in "fc"):
            continue
        elif old.dtype.kind not in "fc":
            bad.append(f"{key}: differs")
        elif not np.array_equal(np.isnan(new), np.isnan(old)):
            bad.append(f"{key}: NaN at other samples")
        else:
            finite = np.isfinite(old)
            scale = float(np.sqrt(np.mean(np.square(old[finite], dtype=np.float64)))) if finite.any() else 0.0
            worst = float(np.max(np.abs(new[finite].astype(np.float64) - old[finite]), initial=0.0))
            if worst > TOLERANCE_OF_RMS * scale:
                bad.append(f"{key}: off by {worst:.3g} (rms {scale:.3g})")
            inexact += 1
    bad += [f"{key}: new field" for key in sorted(set(now) - set(then))]
    return bad, inexact


def test_every_result_field_as_before_the_split(now_and_then):
    now, then = now_and_then
    assert len(then) > 150  # every case and field was stored
    bad, inexact = _differences(now, then)
    print(f"golden: {len(then)} fields, {len(then) - inexact - len(bad)} bit-identical, {inexact} within {TOLERANCE_OF_RMS:g} rms")
    assert bad == []


def test_the_comparison_sees_a_change(now_and_then):
    now, then = now_and_then
    key = "series_full_image/1/height"
    changed = dict(now)
    h = changed[key].copy()
    h[np.isfinite(h)] *= 1 + 1e-3  # a mistake's size, not an FFT plan's
    changed[key] = h
    assert _differences(changed, then)[0] == [f"{key}: off by {np.nanmax(np.abs(h - then[key])):.3g} "
                                              f"(rms {np.sqrt(np.nanmean(then[key].astype(np.float64) ** 2)):.3g})"]
