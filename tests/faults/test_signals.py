"""SIGTERM and SIGHUP end ``tirdeflect record`` like Ctrl-C (issue 7, case 4); a stop signal after a command
ended, while its process exits, is one line and 128 + its number too (``tirdeflect process``, last test).

``timeout``, systemd and a closing terminal send SIGTERM/SIGHUP, not SIGINT.
A real signal goes to a real recording subprocess (synthetic camera, 50
frames/s); the user must get a message, exit 128 + signal number, and a file
closed properly: datasets trimmed to the frames written, ``/summary``, every
frame captured before the signal written (in burst mode too, where the frames
wait in RAM until the end).
"""

import json
import signal

import h5py
import numpy as np
import pytest

from tests.faults.tools import RecordProcess, frames_written_line, wait_until

#: a stopped recording must be closed within this many seconds of the signal
CLOSE_WITHIN_S = 30.0
SYNTHETIC = ("--camera", "synthetic", "--synthetic-size", "128", "--synthetic-frames", "2", "--frame-rate-hz", "50")


def _check_closed(path, n_at_least):
    with h5py.File(path, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        assert f["frames"].shape[0] == n and len(f["frame_table"]) == n, "datasets not trimmed"
        assert "summary" in f and f.attrs["complete"] == 0
        summary = json.loads(f["summary"].attrs["summary_json"])
        table = f["frame_table"][:]
        frames = f["frames"][:]
    assert n >= n_at_least
    # every frame the camera thread got is there (a busy machine may make the camera drop some: then the
    # summary counts exactly those)
    assert list(table["sequence"]) == list(range(n))
    assert summary["lost_upstream_id_gaps"] == int((np.diff(table["frame_id"]) - 1).sum())
    assert np.all(frames.reshape(n, -1).max(axis=1) > 0)
    return n


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_stop_signal_while_writing(tmp_path, sig):
    out = tmp_path / "s.h5"
    rec = RecordProcess(*SYNTHETIC, "--frames", "3000", "--out", str(out))
    try:
        wait_until(lambda: rec.progress() >= 20 or rec.proc.poll() is not None, 120, "20 frames written")
        seen = rec.progress()
        rec.proc.send_signal(sig)
        code, stdout, stderr = rec.wait(CLOSE_WITHIN_S)
    finally:
        rec.kill()
    assert code == 128 + sig, f"exit {code}\n{stdout}\n{stderr}"
    assert f"{signal.Signals(sig).name} received; closing the file" in stderr and "Traceback" not in stderr
    n = _check_closed(out, seen)
    assert frames_written_line(stdout) == n < 3000


def test_sigterm_in_burst_mode_writes_the_frames_in_ram(tmp_path):
    out = tmp_path / "b.h5"
    rec = RecordProcess(*SYNTHETIC, "--frames", "2000", "--burst", "--out", str(out))
    try:
        wait_until(lambda: rec.progress() >= 30 or rec.proc.poll() is not None, 120, "30 frames captured into RAM")
        seen = rec.progress()
        rec.proc.send_signal(signal.SIGTERM)
        code, stdout, stderr = rec.wait(CLOSE_WITHIN_S)
    finally:
        rec.kill()
    assert code == 143, f"exit {code}\n{stdout}\n{stderr}"
    n = _check_closed(out, seen)  # every frame captured before the signal is in the file
    assert frames_written_line(stdout) == n < 2000


def test_ctrl_c_before_the_command_began_is_one_line_not_a_traceback(tmp_path):
    """By-hand trial of 7 Dec 2026: Ctrl-C 0.3 s after `tirdeflect record ...` started (while it imported and
    parsed) printed a 65-line KeyboardInterrupt traceback and the process died by the signal. A real SIGINT
    sent by the process to itself while it builds its parser: one line, exit 130, no file."""
    import os
    import subprocess
    import sys

    out = tmp_path / "x.h5"
    script = ("import os, signal, sys\n"
              "import importlib\n"
              "m = importlib.import_module('app.cli.main')\n"
              "build = m.build_parser\n"
              "def interrupted_build():\n"
              "    os.kill(os.getpid(), signal.SIGINT)\n"
              "    return build()\n"
              "m.build_parser = interrupted_build\n"
              f"sys.exit(m.main(['record', *{list(SYNTHETIC)!r}, '--frames', '50', '--out', {str(out)!r}]))\n")
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr and "interrupted before the command began" in proc.stderr, proc.stderr
    assert not out.exists()


#: ``tirdeflect`` as the program (``main()`` reads its own command line), with a thread that holds the
#: interpreter's exit (threading's shutdown joins it) once the command has ended, until the test has sent its
#: signal; and an object whose deletion says when the interpreter frees the modules, where Python 3.11 no longer
#: handles signals (a Ctrl-C there killed the process: status -2)
_EXIT_HELD_CHILD = """
import os, sys, threading, time
release = sys.argv.pop(1)


def hold_the_exit():
    while threading.main_thread().is_alive():  # the main thread stops as the interpreter begins to exit
        time.sleep(0.01)
    os.write(2, b"exit held\\n")
    while not os.path.exists(release):
        time.sleep(0.01)


threading.Thread(target=hold_the_exit, name="hold the exit").start()


class FreedWithTheModules:
    def __del__(self, write=os.write):
        write(2, b"modules freed\\n")


freed_with_the_modules = FreedWithTheModules()
from app.cli.main import main
sys.exit(main())
"""


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Two ray-traced frames of 128 px and their reference and geometry."""
    from app.cli import main

    d = tmp_path_factory.mktemp("exit-sim")
    assert main(["simulate", "--out", str(d), "--size", "128", "--frames", "2"]) == 0
    return d


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stop_signal_after_the_output_was_written_is_one_line_and_leaves_it_whole(sim, tmp_path, sig):
    """Ctrl-C after `tirdeflect process` printed "wrote N frame(s)", while the process exits: it raised
    KeyboardInterrupt inside the interpreter's teardown ("Exception ignored ..." and a traceback, exit 0) or,
    later in it, killed the process (exit -2); SIGTERM killed it (-15). Now: one line, 128 + the signal's
    number, and the output, complete before the signal, stays as it was written."""
    import subprocess
    import sys

    from tests.faults.tools import ROOT
    from tests.helpers import stderr_until_signalled

    out, release = tmp_path / "out.h5", tmp_path / "release"
    proc = subprocess.Popen(
        [sys.executable, "-c", _EXIT_HELD_CHILD, str(release), "process", str(sim / "reference.png"),
         str(sim / "frame_0000.png"), str(sim / "frame_0001.png"), "--geometry", str(sim / "geometry.toml"),
         "--out", str(out), "--no-progress", "--workers", "1"],
        cwd=ROOT, stderr=subprocess.PIPE, text=True,
        # as at a terminal: a test runner started in the background may ignore SIGINT
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []

    def signal_while_it_exits(line):
        seen.append(line)
        if line.strip() != "exit held":
            return False
        proc.send_signal(sig)
        release.touch()  # the exit goes on once the signal is sent
        return True

    code, err = stderr_until_signalled(proc, signal_while_it_exits)
    assert any(line.startswith("tirdeflect: wrote 2 frame(s) to") for line in seen), err
    assert seen[-1].strip() == "exit held", err  # the signal came after the command had ended
    name = "Ctrl-C" if sig == signal.SIGINT else signal.Signals(sig).name
    assert code == 128 + sig, err
    said = [line for line in err.splitlines() if "interrupted" in line]
    assert said == [f"tirdeflect: interrupted ({name}) while exiting, after the command had ended (status 0) "
                    "and closed its files; nothing was lost"], err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    # ended before the interpreter frees its modules, where a signal ends the process outright
    assert "modules freed" not in err, err
    assert not list(tmp_path.glob("out.partial*")) and not list(tmp_path.glob(".out.partial*"))
    with h5py.File(out, "r") as f:
        assert f.attrs["status"] == "complete" and int(f.attrs["frames_done"]) == 2
        assert f["height"].shape[0] == 2 and np.isfinite(f["height"][()]).mean() > 0.9
