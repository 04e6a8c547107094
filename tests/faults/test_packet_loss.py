"""GigE packet loss during ``tirdeflect record`` (issue 7, case 3).

The fake GigE camera drops ``-r`` packets per thousand. Packet resend is on
(Aravis asks again for every lost packet), but ``arv-fake-gv-camera-0.8``
never answers a resend request (its GVCP handler has no PACKETRESEND), so the
losses stay. What the user must get: the pixels that did arrive kept (no
black frames), every incomplete frame flagged in the frame table with the
bytes it misses, the summary saying "N of M frames incomplete" with the same
N as the file, and exit status 1.
"""

import json
import re

import h5py
import numpy as np
import pytest

from tests.faults.tools import RecordProcess

N_FRAMES = 120


def _record_lossy(tmp_path, loss_per_thousand):
    from tests.drivers.fixtures import FakeGvCamera, _aravis_or_skip

    _aravis_or_skip()
    out = tmp_path / f"loss{loss_per_thousand}.h5"
    with FakeGvCamera(loss_per_thousand=loss_per_thousand) as fake:
        rec = RecordProcess("--camera", fake.camera_id, "--frames", str(N_FRAMES), "--frame-rate-hz", "40",
                            "--out", str(out), "--no-progress")
        try:
            code, stdout, stderr = rec.wait(120)
        finally:
            rec.kill()
    return out, code, stdout, stderr


@pytest.mark.aravis
@pytest.mark.parametrize("loss_per_thousand", [20, 2])
def test_lost_packets_are_flagged_counted_and_the_rest_kept(tmp_path, loss_per_thousand):
    out, code, stdout, stderr = _record_lossy(tmp_path, loss_per_thousand)
    with h5py.File(out, "r") as f:
        table = f["frame_table"][:]
        frames = f["frames"][:]
        summary = json.loads(f["summary"].attrs["summary_json"])
    n = len(table)
    assert n == N_FRAMES and np.all(np.diff(table["frame_id"]) == 1)
    flagged = (table["flags"] & 1) != 0  # FrameFlags.INCOMPLETE
    missing = table["missing_bytes"]
    # a frame is flagged exactly when bytes are missing, and the file, the summary and the exit status agree
    assert np.array_equal(flagged, missing > 0)
    n_incomplete = int(flagged.sum())
    assert summary["incomplete"] == n_incomplete and summary["incomplete_missing_bytes"] == int(missing.sum())
    if n_incomplete:
        assert code == 1, f"exit {code}\n{stdout}\n{stderr}"
        assert re.search(rf"\b{n_incomplete} of {n} frames incomplete", stdout), stdout
    else:
        assert code == 0
    # the pixels that arrived are kept: the fake's diagonal ramp holds wherever both neighbours arrived,
    # and a frame has zeros only where bytes were lost (plus the ramp's own zeros, one value in 256)
    for img, miss in zip(frames, missing):
        a, b = img[1:, :-1], img[:-1, 1:]
        both = (a > 0) & (b > 0)
        assert np.array_equal(a[both], b[both])
        zeros = int((img == 0).sum())
        assert miss <= zeros <= miss + 2 * img.size // 256 + 2 * img.shape[0]
    lost_share = missing.sum() / frames.size
    complete = 1 - n_incomplete / n
    print(f"-r {loss_per_thousand}: {n - n_incomplete} of {n} frames complete ({100 * complete:.0f} %), "
          f"{100 * lost_share:.2f} % of all bytes lost; resend requests {summary.get('packets_resend_requests')}, "
          f"packets resent {summary.get('packets_resent')}")
    # what was lost matches the loss rate the fake was given (binomial over ~190 packets a frame): within 3x
    assert lost_share < 3 * loss_per_thousand / 1000
