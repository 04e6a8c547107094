"""TIFF stacks cut short and frame files that cannot be opened, through `tirdeflect process`.

A stack whose copy was interrupted loses its end. ImageJ and tifffile (by default)
store every image directory but the first after all the pixels, so the cut takes
them all: tifffile then lists one page and only logs `invalid page offset`, and the
run wrote 1 frame of 4 with exit 0 (the sweep's finding F1). Every frame the file
declares must come out: the whole ones measured as from the uncut file, each one
the cut took an UNREADABLE row whose reason says the file is truncated, exit 3, and
none of tifffile's own log lines on the terminal. An empty or damaged frame file in
the middle of the list (finding F1b) likewise stands for one UNREADABLE frame
instead of ending the run with exit 2.

The stacks are written by tifffile (ImageJ hyperstack, tifffile's contiguous
default, one page at a time as a camera program appends them) from ray-traced
frames and then really cut on disk.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from app.files import imageio

ROOT = Path(__file__).resolve().parents[2]
UNREADABLE = 5  # app.batch.frame_status.FrameStatus.UNREADABLE
DECLARED = 4  # frames in every stack below


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A ray-traced 12-bit bump (128 x 128 px): reference, 3 frames, geometry."""
    d = tmp_path_factory.mktemp("simtiff")
    r = _cli("simulate", "--out", d, "--surface", "bump", "--size", "128", "--frames", "3",
             "--bits", "12", "--noise", "2", "--overwrite")
    assert r.returncode == 0, r.stderr
    return d


def _frames(sim: Path) -> np.ndarray:
    """The 4 frames of the stacks: the 3 simulated ones, then the first again (uint16)."""
    frames = [imageio.read_image(sim / f"frame_{k:04d}.tif") for k in range(3)]
    return np.stack(frames + frames[:1]).astype(np.uint16)


def _write_stack(path: Path, frames: np.ndarray, layout: str) -> Path:
    if layout == "imagej":  # ImageJ hyperstack: page 0's directory, the pixels, then the others
        tifffile.imwrite(path, frames, imagej=True)
    elif layout == "contiguous":  # tifffile's default: {"shape": [4, 128, 128]} on page 0
        tifffile.imwrite(path, frames, photometric="minisblack")
    else:  # a directory before each page's pixels, as a camera program appends them
        with tifffile.TiffWriter(path) as w:
            for image in frames:
                w.write(image, photometric="minisblack", contiguous=False)
    return path


def _cut(path: Path, fraction: float, out: Path) -> tuple:
    """``out``: the first ``fraction`` of ``path``'s bytes; and how many of its frames
    still have all their pixels in it (frames are stored in order in every layout)."""
    data = path.read_bytes()
    keep = int(len(data) * fraction)
    out.write_bytes(data[:keep])
    with tifffile.TiffFile(path) as tif:
        ends = [int(p.dataoffsets[-1]) + int(p.databytecounts[-1]) for p in tif.pages]
    assert len(ends) == DECLARED
    return out, sum(end <= keep for end in ends)


def _read(out: Path) -> dict:
    with h5py.File(out, "r") as f:
        return {"expected": int(f.attrs["frames_expected"]), "done": int(f.attrs["frames_done"]),
                "frame_status": f["frame_status"][()], "height": f["height"][()],
                "text": list(f["frame_status_text"].asstr()[()])}


CASES = [("imagej", 0.97), ("imagej", 0.6), ("contiguous", 0.6), ("pages", 0.6)]


@pytest.mark.parametrize("layout", ["imagej", "contiguous", "pages"])
@pytest.mark.parametrize("fraction", [0.97, 0.6])
def test_a_cut_stack_gives_every_frame_it_declares(sim, tmp_path, caplog, layout, fraction):
    """The reader: as many frames as the file declares; the whole ones exactly the
    pixels written (also those whose directories the cut took), the others errors
    that say the file is truncated and name it and the frame; tifffile's own log
    records kept from the log."""
    frames = _frames(sim)
    whole = _write_stack(tmp_path / "whole.tif", frames, layout)
    cut, kept = _cut(whole, fraction, tmp_path / "cut.tif")
    assert 1 <= kept < DECLARED
    caplog.set_level(logging.DEBUG)
    assert imageio.frame_count(cut) == DECLARED
    items = list(imageio.iter_frames([cut], errors="yield"))
    assert [item.index_in_source for item in items] == list(range(DECLARED))
    for item in items[:kept]:
        np.testing.assert_array_equal(item.image, frames[item.index_in_source])
    for item in items[kept:]:
        text = str(item.error)
        assert item.image is None and "truncated" in text and str(cut) in text, text
        assert f"frame {item.index_in_source} " in text or f"page {item.index_in_source} " in text, text
        assert "copy the file again" in text
    assert not [r for r in caplog.records if r.name.startswith("tifffile")]
    with pytest.raises(imageio.ImageReadError, match="truncated"):
        imageio.read_image(cut, index=DECLARED - 1)


@pytest.mark.parametrize("layout,fraction", CASES)
def test_process_stores_the_frames_a_cut_stack_lost_as_unreadable(sim, tmp_path, layout, fraction):
    """`tirdeflect process REF CUT.tif`: every declared frame is a row of the output, the
    cut ones UNREADABLE with the truncation as reason, the whole ones measured as from
    the uncut stack, exit 3 (incomplete), and no `invalid page offset` on the terminal."""
    frames = _frames(sim)
    whole = _write_stack(tmp_path / "whole.tif", frames, layout)
    cut, kept = _cut(whole, fraction, tmp_path / "cut.tif")
    out = tmp_path / "out.h5"
    r = _cli("process", sim / "reference.tif", cut, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress")
    assert r.returncode == 3, r.stderr
    assert "invalid page offset" not in r.stderr and "<tifffile." not in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and "ERROR" not in r.stderr, r.stderr
    assert f"wrote {DECLARED} frame(s)" in r.stderr and "truncated" in r.stderr
    o = _read(out)
    assert o["expected"] == o["done"] == len(o["frame_status"]) == DECLARED
    assert list(o["frame_status"][kept:]) == [UNREADABLE] * (DECLARED - kept)
    assert all(s != UNREADABLE for s in o["frame_status"][:kept])
    for k in range(kept, DECLARED):
        assert "truncated" in o["text"][k] and str(cut) in o["text"][k], o["text"][k]
    assert not np.isfinite(o["height"][kept:]).any()
    # the frames the cut stack still holds are measured as from the whole stack
    r = _cli("process", sim / "reference.tif", whole, "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "whole.h5", "--no-progress")
    assert r.returncode == 0, r.stderr
    np.testing.assert_array_equal(o["height"][:kept], _read(tmp_path / "whole.h5")["height"][:kept])


def test_an_empty_or_damaged_frame_file_in_the_list_is_one_unreadable_frame(sim, tmp_path):
    """An empty TIFF and one cut inside its header, between good frames: each is one
    UNREADABLE row naming the file, the run goes on and exits 3 (it ended with exit 2,
    nothing written, while a TIFF cut in its pixels was already such a row)."""
    empty = tmp_path / "empty.tif"
    empty.write_bytes(b"")
    header = tmp_path / "header.tif"
    header.write_bytes((sim / "frame_0001.tif").read_bytes()[:100])
    out = tmp_path / "out.h5"
    inputs = [sim / "frame_0000.tif", empty, sim / "frame_0001.tif", header, sim / "frame_0002.tif"]
    r = _cli("process", sim / "reference.tif", *inputs, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress")
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    o = _read(out)
    assert o["expected"] == o["done"] == 5
    assert list(o["frame_status"] == UNREADABLE) == [False, True, False, True, False]
    assert str(empty) in o["text"][1] and "empty (0 bytes)" in o["text"][1]
    assert str(header) in o["text"][3] and "truncated" in o["text"][3] and "100 bytes" in o["text"][3]


def test_a_recording_that_cannot_be_opened_is_still_refused_before_the_run(sim, tmp_path):
    """An empty recording (.h5) among the frames: how many frames it held is unknown, so
    every frame number after it would be off: refused up front, naming the file (exit 2)."""
    empty = tmp_path / "empty.h5"
    empty.write_bytes(b"")
    r = _cli("process", sim / "reference.tif", sim / "frame_0000.tif", empty, "--geometry",
             sim / "geometry.toml", "--out", tmp_path / "out.h5", "--no-progress")
    assert r.returncode == 2, r.stderr
    assert str(empty) in r.stderr and "empty" in r.stderr
    assert not (tmp_path / "out.h5").exists()


def test_tifffile_logs_as_before_outside_the_reader(caplog):
    """The reader keeps tifffile's records only while it reads: others still log."""
    caplog.set_level(logging.ERROR)
    logging.getLogger("tifffile").error("outside the reader")
    assert [r.getMessage() for r in caplog.records if r.name == "tifffile"] == ["outside the reader"]
