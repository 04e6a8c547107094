"""An output asked for where no file can be created (finding F6 of the by-hand trial), through the CLI.

``tirdeflect process ... --out /proc/m13.h5`` printed HDF5's "[Errno 2] Unable to synchronously
create file (... flags = 15, o_flags = c2)" (``os.access`` says yes to root there). Every command
that writes a file now tries, before any frame is processed or recorded, to create one where it was
asked for (:func:`app.files.h5safe.check_creatable`), and says why it cannot, from the errno, and
which option to change. ``/proc`` is the place every Linux machine has where no file can be created
(as root too); the errnos a test cannot make there (permission denied, read-only, full) are put to
the message function itself. Data sets are made by the project's own ``tirdeflect simulate``.
"""

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import main
from app.files import h5safe

ROOT = Path(__file__).resolve().parents[2]
SIZE = 128
#: a folder that exists and takes no new files, for every user
NO_FILES_HERE = Path("/proc")


def _proc_takes_no_files() -> bool:
    try:
        with open(NO_FILES_HERE / "tirdeflect-probe", "x"):
            pass
    except OSError:
        return True
    os.unlink(NO_FILES_HERE / "tirdeflect-probe")  # pragma: no cover - not Linux's /proc
    return False


pytestmark = pytest.mark.skipif(not (sys.platform.startswith("linux") and NO_FILES_HERE.is_dir()
                                     and _proc_takes_no_files()),
                                reason="needs Linux's /proc (a folder where no file can be created)")


def _cli(*args):
    """``tirdeflect ARGS`` as a user runs it: (exit status, stdout + stderr)."""
    r = subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT, text=True,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=300)
    return r.returncode, r.stdout


def _says_where_and_what_to_do(text, path, option="--out"):
    assert f"cannot create the output file {str(path)!r}" in text or "permission denied" in text, text
    assert f"choose another {option}" in text, text
    for raw in ("Unable to synchronously", "flags =", "Errno", "Traceback", "check the path"):
        assert raw not in text, text


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A ray-traced 12-bit set of 2 frames (reference.tif, frame_000N.tif, geometry.toml, heights.h5)."""
    d = tmp_path_factory.mktemp("outloc") / "sim"
    assert main(["simulate", "--out", str(d), "--size", str(SIZE), "--frames", "2", "--bits", "12"]) == 0
    return d


def test_process_into_a_folder_that_takes_no_files_is_refused_before_any_frame(sim):
    """F6: `process ... --out /proc/m13.h5 --overwrite`: refused with the reason and --out to change, before
    any frame is processed (no "wrote" summary, no frame named)."""
    out = NO_FILES_HERE / "m13.h5"
    code, text = _cli("process", sim / "reference.tif", sim / "frame_0000.tif", "--geometry", sim / "geometry.toml",
                      "--out", out, "--overwrite", "--no-progress")
    assert code == 2, text
    _says_where_and_what_to_do(text, out)
    assert "the folder '/proc' takes no new files" in text or "permission denied" in text
    assert "wrote" not in text and "frame 0" not in text


@pytest.mark.parametrize("space_check", [True, False])
def test_record_into_a_folder_that_takes_no_files_is_refused_before_the_camera_opens(tmp_path, space_check):
    """`record --out /proc/r.h5`: HDF5's text with --no-space-check, else "needs 16.79 MB but only 0 B are
    free on '/proc'; free space" (there is no disk to free); now the reason, before a camera is opened."""
    out = NO_FILES_HERE / "r.h5"
    code, text = _cli("record", "--camera", "synthetic", "--frames", "3", "--synthetic-size", "64",
                      "--no-progress", "--out", out, *([] if space_check else ["--no-space-check"]))
    assert code == 2, text
    _says_where_and_what_to_do(text, out)
    assert "free space" not in text


def test_probe_names_the_option_of_the_file_it_cannot_create(sim, tmp_path):
    """`probe OUT.h5 --h5 /proc/p.h5` printed HDF5's text after writing the CSV; now neither is written and
    the message names --h5. A CSV there said "file ... does not exist; check the path"."""
    out = tmp_path / "out.h5"
    assert main(["process", str(sim / "reference.tif"), str(sim / "frame_0000.tif"), "--geometry",
                 str(sim / "geometry.toml"), "--out", str(out), "--no-progress"]) == 0
    csv = tmp_path / "p.csv"
    code, text = _cli("probe", out, "--at", "0,0", "--out", csv, "--h5", NO_FILES_HERE / "p.h5")
    assert code == 2, text
    _says_where_and_what_to_do(text, NO_FILES_HERE / "p.h5", "--h5")
    assert not csv.exists()
    code, text = _cli("probe", out, "--at", "0,0", "--out", NO_FILES_HERE / "p.csv")
    assert code == 2, text
    _says_where_and_what_to_do(text, NO_FILES_HERE / "p.csv")


def test_movie_into_a_folder_that_takes_no_files_is_refused_before_any_frame_is_drawn(sim, tmp_path):
    """`movie OUT.h5 --out /proc/m.mp4` said "[Errno 2] No such file or directory" once PyAV opened it."""
    pytest.importorskip("av")
    out = tmp_path / "out.h5"
    assert main(["process", str(sim / "reference.tif"), str(sim / "frame_0000.tif"), "--geometry",
                 str(sim / "geometry.toml"), "--out", str(out), "--no-progress"]) == 0
    code, text = _cli("movie", out, "--out", NO_FILES_HERE / "m.mp4")
    assert code == 2, text
    _says_where_and_what_to_do(text, NO_FILES_HERE / "m.mp4")


def test_simulate_into_a_folder_that_takes_no_files_is_refused_before_the_ray_tracing():
    """`simulate --out /proc/sim` said "file '/proc/sim' does not exist; check the path" after ray tracing
    every frame; now the reason names the folder where nothing can be created."""
    code, text = _cli("simulate", "--out", NO_FILES_HERE / "sim", "--size", SIZE)
    assert code == 2, text
    _says_where_and_what_to_do(text, NO_FILES_HERE / "sim" / "heights.h5")
    assert "the folder '/proc' takes no new files" in text or "permission denied" in text


def test_the_recording_file_says_why_it_cannot_be_created():
    """The recorder under the window and `record` (app.capture.recorder.RecordingFile) turned HDF5's
    text into "cannot create '...': [Errno 2] Unable to synchronously create file ...; free disk space"."""
    import numpy as np

    from app.capture.recorder import RecorderError, RecordingFile

    with pytest.raises(RecorderError) as info:
        RecordingFile(NO_FILES_HERE / "rec.h5", shape=(8, 8), dtype=np.uint8, n_frames=1, check_space=False)
    _says_where_and_what_to_do(str(info.value), NO_FILES_HERE / "rec.h5", "folder")


@pytest.mark.parametrize("code, reason", [
    (errno.EACCES, "permission denied: you may not create files in '{folder}'"),
    (errno.EROFS, "'{folder}' is on a read-only file system"),
    (errno.ENOSPC, "the disk holding '{folder}' is full"),
    (errno.ENOENT, "the folder '{folder}' takes no new files"),
])
def test_the_reason_comes_from_the_errno(tmp_path, code, reason):
    """What a user who is not root, or a read-only or full disk, sees: the errno in words, the
    file, the option to change; HDF5's text nowhere."""
    path = tmp_path / "out.h5"
    hdf5_text = f"Unable to synchronously create file (errno = {code}, flags = 15, o_flags = c2)"
    error = h5safe.cannot_create(path, OSError(code, hdf5_text), "choose another --out")
    text = str(error)
    assert text.startswith(f"cannot create the output file {str(path)!r}: {reason.format(folder=tmp_path)}")
    assert text.endswith("; choose another --out") and "Unable to synchronously" not in text


def test_pattern_into_a_folder_that_takes_no_files_says_why_and_a_good_place_still_works(tmp_path):
    """`pattern --out /proc/b.pdf` said "file '/proc/b.pdf' does not exist; check the path"."""
    code, text = _cli("pattern", "--period-mm", "2", "--size-mm", "150,150", "--out", NO_FILES_HERE / "b.pdf")
    assert code == 2, text
    _says_where_and_what_to_do(text, NO_FILES_HERE / "b.pdf")
    code, text = _cli("pattern", "--period-mm", "2", "--size-mm", "150,150", "--out", tmp_path / "b.pdf")
    assert code == 0 and (tmp_path / "b.pdf").stat().st_size > 0, text
    assert not list(tmp_path.glob(".tirdeflect-probe-*"))  # the creation test leaves nothing behind
