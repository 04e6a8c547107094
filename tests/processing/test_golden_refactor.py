"""Every Result field as before the split of processing/reconstruct.py (issue 19).

How the golden file was made: tests/data/golden/reconstruct_golden.npz holds
every Result field of nine ray-traced 128^2 cases (checkerboard full grid with
the default image refinement and with FD, decimated grid, series of two frames
with temporal unwrapping and the series check, full-size inverse FFTs, random
dots, FS-SS, a frame with a blank part and ray crossings), written by
tests/data/golden/make_golden.py run on the code before the split (commit
3173c53, in a throwaway ``git worktree``, with make_golden.py as it is now),
under make_golden's fixed FFT setting: FFTW_ESTIMATE on one thread through the
public options (``planner_effort``, ``threads``) and FFTW's wisdom set aside
(``fixed_fft_plans``).  The file first committed (3173c53, written in a fresh
process with the default options) is equal to that run array for array, bit
for bit, so it stayed.

What varied before: FFTW uses whatever wisdom the process holds for a
transform, even for an FFTW_ESTIMATE plan, so after an FFTW_MEASURE plan of
the same shape (the app's setting, GUI and app tests in the same pytest
process, wisdom imported from the app's cache) the same code took other
plans: 66 of the 204 fields then came out up to 2.7e-5 of their RMS from the
file (measured by planting FFTW_MEASURE wisdom for these cases first; a
fresh-clone run of the whole suite had shown 2.6e-5).  The fixture plants such
wisdom on purpose before the run, so the test holds whatever ran before it.

Under the fixed setting the code as it is now must give the same numbers
as it did before the split.  On the machine that wrote the file that meant
bit-identical (the issue's bound, 1e-6 of the field's RMS, needed by none).
On another processor the same code and the same libraries round differently
(numpy's and FFTW's vector loops and Numba's kernels pick the processor's
widest SIMD units, so sums run in another order): on an AMD EPYC with AVX-512
the nine cases differ from the file by at most 1.0e-5 of a field's RMS as an
RMS difference and 1.7e-4 of its RMS at the worst sample (the masked frame
with image refinement, whose iterative solve carries last bits on), and the
carriers, kept as text, in their float32 last bit (7e-8).  So float fields
must agree within 5e-5 of their RMS as an RMS difference and 1e-3 at every
sample, numbers inside text within 1e-6 relative, everything else (booleans,
shapes, the rest of the text) exactly.  A refactor's real mistakes (a lost
term, stages out of order, a 2 pi slip, a wrong carrier) are 1e-3 and more
and fail; so does a 1e-4 change of a whole field, 10 times below the 0.1 %
that heights are judged by.
"""

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
#: a float field's RMS difference from the file, as a fraction of the field's RMS (measured across
#: processors: 1.0e-5)
RMS_DIFFERENCE_OF_RMS = 5e-5
#: a float field's largest difference at one sample, as a fraction of the field's RMS (measured across
#: processors: 1.7e-4)
WORST_DIFFERENCE_OF_RMS = 1e-3
#: numbers inside text fields (carriers, pin region, series state), relative (measured: 7e-8, float32's
#: last bit)
TEXT_NUMBER_RELATIVE = 1e-6
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
#: PinStatus fields added after the golden file was made (5 Dec 2026: how far the pattern moved on the
#: pin samples; 6 Dec 2026: how far the whole frame's moved alike, and what that does to the heights;
#: 7 Dec 2026: the image's scale change on the pin samples: measures of the frame, not a change of the
#: chain; the connected pieces pinned apart, 7 Dec 2026): left out of the comparison (the cases rewritten since
#: hold some of them, the others do not)
_NEWER_PIN_FIELD = re.compile(
    r", '(?:pieces|region_motion_px|frame_motion_px|frame_shift_share|frame_motion_row_px|frame_motion_col_px|shift_effect_um"
    r"|shift_level_um|shift_removed|region_scale|region_scale_reach_px|region_scale_explained)': [^,}]*")
#: SeriesCheck's field added after (7 Dec 2026: the frame unwrapped in space alone where the series' count
#: slipped), left out where it is False: a golden series frame measured alone now would still differ
_NEWER_SERIES_FIELD = re.compile(r", unwrapped_alone=False\)$")


def _older_text(text: str) -> str:
    """``text`` without the fields added since the golden file was made (at their values of then)."""
    return _NEWER_SERIES_FIELD.sub(")", _NEWER_PIN_FIELD.sub("", text))


def _same_text(new: str, old: str) -> bool:
    """Equal text, or equal but for numbers within TEXT_NUMBER_RELATIVE of each other."""
    if new == old:
        return True
    if _NUMBER.sub("#", new) != _NUMBER.sub("#", old):
        return False
    a = np.array([float(x) for x in _NUMBER.findall(new)])
    b = np.array([float(x) for x in _NUMBER.findall(old)])
    return bool(np.all(np.abs(a - b) <= TEXT_NUMBER_RELATIVE * np.abs(b)))


def _maker():
    spec = importlib.util.spec_from_file_location("make_golden", GOLDEN / "make_golden.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _plant_measured_wisdom(maker):
    """FFTW_MEASURE plans of every case's transforms, as an earlier test (or the
    app's wisdom cache) would leave in the process: without the fixed setting
    they change the golden run's plans."""
    from processing.reconstruct import Reconstructor

    for ref, frames, geometry, opts in maker.cases().values():
        Reconstructor(ref, geometry, **opts, planner_effort="FFTW_MEASURE", threads=1)(frames[0])


@pytest.fixture(scope="module")
def now_and_then():
    with np.load(GOLDEN / "reconstruct_golden.npz") as f:
        then = {k: f[k] for k in f.files}
    maker = _maker()
    _plant_measured_wisdom(maker)
    return maker.run_all(), then


def _differences(now, then):
    bad, inexact = [], 0
    for key in sorted(then):
        old = then[key]
        if key not in now:
            bad.append(f"{key}: missing")
            continue
        new = now[key]
        if old.dtype.kind == "U" and old.shape == () and new.dtype.kind == "U" and new.shape == ():
            if not _same_text(_older_text(str(new)), _older_text(str(old))):
                bad.append(f"{key}: differs: {new} (was {old})")
            inexact += str(new) != str(old)
            continue
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
            diff = np.abs(new[finite].astype(np.float64) - old[finite])
            worst = float(np.max(diff, initial=0.0))
            rms = float(np.sqrt(np.mean(np.square(diff)))) if diff.size else 0.0
            if rms > RMS_DIFFERENCE_OF_RMS * scale or worst > WORST_DIFFERENCE_OF_RMS * scale:
                bad.append(f"{key}: off by {rms:.3g} rms, {worst:.3g} at worst (rms {scale:.3g})")
            inexact += 1
    bad += [f"{key}: new field" for key in sorted(set(now) - set(then))]
    return bad, inexact


def test_every_result_field_as_before_the_split(now_and_then):
    now, then = now_and_then
    assert len(then) > 150  # every case and field was stored
    bad, inexact = _differences(now, then)
    print(f"golden: {len(then)} fields, {len(then) - inexact} bit-identical, {inexact} not (within the bounds)")
    assert bad == []


@pytest.mark.parametrize("relative", [1e-3, 1e-4])
def test_the_comparison_sees_a_change(now_and_then, relative):
    """A mistake's size (1e-3) fails, and so does 1e-4 of a whole field, 2x the
    bound and 10x the spread between processors."""
    now, then = now_and_then
    key = "series_full_image/1/height"
    changed = dict(now)
    h = changed[key].copy()
    h[np.isfinite(h)] *= 1 + relative
    changed[key] = h
    bad = _differences(changed, then)[0]
    assert [b.split(":")[0] for b in bad] == [key]


def test_the_comparison_sees_a_carrier_moved_by_1e_5():
    """A carrier 1e-5 off (a refactor that estimates it from another spectrum) fails;
    its float32 last bit (7e-8) does not."""
    key = "ifft_full/0/carriers"
    old = {key: np.array("[[-0.08717214316129684, 0.049998171627521515]]")}
    last_bit = {key: np.array("[[-0.08717214316129684, 0.049998167902231216]]")}
    moved = {key: np.array("[[-0.08717214316129684, 0.0499986715]]")}
    assert _differences(last_bit, old)[0] == []
    assert [b.split(":")[0] for b in _differences(moved, old)[0]] == [key]
