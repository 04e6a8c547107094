"""Argument errors of ``tirdeflect record`` are answered before any camera is opened (issue 7, case 7).

The camera is ``aravis:198.51.100.7`` (TEST-NET-2: nothing answers there), so any
answer that needed the camera would come after Aravis' timeouts, and would
talk about the camera instead of the argument.
"""

import re
import subprocess
import sys
import time

import pytest

from tests.faults.tools import ROOT

NOWHERE = "aravis:198.51.100.7"
#: an argument error comes before the camera is tried (its message names the argument, never the
#: camera): Python start-up and imports only, 0.5-1.5 s quiet. A hang detector, >= 10x above need
ANSWER_WITHIN_S = 20.0


def _record(tmp_path, *args):
    out = tmp_path / "never.h5"
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "app.cli", "record", "--out", str(out), "--no-progress", *args],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    assert not out.exists(), "a refused recording left a file"
    return r, took


@pytest.mark.parametrize("args, says", [
    (("--pre", "-5", "--post", "10"), "--pre must be >= 0 frames; got -5"),
    (("--pre", "5", "--post", "0"), "--post must be >= 1"),
    (("--frames", "0"), "--frames must be >= 1; got 0"),
    (("--frames", "10", "--frame-rate-hz", "-3"), "--frame-rate-hz must be > 0 Hz"),
    (("--frames", "10", "--ring-frames", "1"), "--ring-frames must be >= 2"),
    (("--pre-s", "-1", "--post", "3"), "--pre-s must be >= 0 seconds"),
    (("--pre", "3", "--pre-s", "1", "--post", "3"), "either --pre (frames) or --pre-s"),
    (("--frames", "10", "--roi", "0,0,0,64"), "--roi needs"),
    (("--pre", "5", "--post", "5", "--trigger", "auto"), "--trigger auto needs --geometry"),
])
def test_argument_errors_come_before_the_camera(tmp_path, args, says):
    r, took = _record(tmp_path, "--camera", NOWHERE, *args)
    assert r.returncode == 2
    assert r.stderr.strip() == f"tirdeflect record: error: {r.stderr.strip().split('error: ', 1)[1]}"
    assert says in r.stderr and "Traceback" not in r.stderr and NOWHERE not in r.stderr, r.stderr
    assert took < ANSWER_WITHIN_S, f"answered after {took:.1f} s"


@pytest.mark.parametrize("camera", ["synthetic", NOWHERE])
def test_pre_trigger_frames_beyond_ram_are_refused_at_once_naming_the_ram(tmp_path, camera):
    """1e6 pre-trigger frames of 512x512 (262 GB) must sit in RAM: refused at once, with the RAM named."""
    extra = ("--roi", "0,0,512,512") if camera == NOWHERE else ("--synthetic-size", "512")
    r, took = _record(tmp_path, "--camera", camera, "--pre", "1000000", "--post", "10", *extra)
    assert r.returncode == 2 and took < ANSWER_WITHIN_S, (took, r.stderr)
    # 1e6 x 512 x 512 bytes (+ 44 bytes of metadata each) = 262 GB
    assert re.search(r"must be held in RAM \(262\.\d\d GB\)", r.stderr) and re.search(r"of the [\d.]+ GB available",
                                                                                      r.stderr), r.stderr
    assert "enlarge the ring" not in r.stderr


@pytest.mark.parametrize("value", ["-1", "0", "nan"])
def test_cameras_refuses_a_discovery_time_that_is_no_time(value):
    """By-hand trial of 7 Dec 2026: `tirdeflect cameras --timeout-s -1` listed nothing and exited 0, as if no
    camera were there. Refused in one line, exit 2."""
    r = subprocess.run([sys.executable, "-m", "app.cli", "cameras", "--timeout-s", value], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--timeout-s must be > 0 seconds" in r.stderr and "camera id" not in r.stdout, r
