"""Truncated camera files and videos through `tirdeflect process`, as a user meets them.

Each file is written by its format's own library (PyAV encodes the videos; the
Phantom CINE is a real file of the project's, its pixels replaced by ray-traced
frames) and then really cut short: the frames its header (or container) promises
but the file no longer holds must come out as UNREADABLE frames with exit
status 3, the frames it still holds processed and written as from the whole
file, and never a traceback.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.files import imageio

av = pytest.importorskip("av")

ROOT = Path(__file__).resolve().parents[2]
CINE_781 = Path(__file__).parent / "data" / "cine" / "cine_781.cine"
UNREADABLE = 5  # app.batch.frame_status.FrameStatus.UNREADABLE
RATE = 25  # frames/s of the videos: 20 frames are 0.8 s


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)


def _simulate(out: Path, size: int, frames: int) -> tuple:
    r = _cli("simulate", "--out", out, "--surface", "waves", "--size", size, "--frames", frames,
             "--bits", "12", "--noise", "1.0", "--overwrite")
    assert r.returncode == 0, r.stderr
    reference = imageio.read_image(out / "reference.tif")
    return [reference] + [imageio.read_image(out / f"frame_{k:04d}.tif") for k in range(frames)]


@pytest.fixture(scope="module")
def sim128(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim128")
    return out, _simulate(out, 128, 19)  # the reference and 19 frames: 20 frames


def _write_video(path: Path, frames, codec: str, pix_fmt: str) -> Path:
    rows, cols = frames[0].shape
    options = {"movflags": "faststart"} if path.suffix in (".mp4", ".mov") else {}
    with av.open(str(path), "w", options=options) as container:
        stream = container.add_stream(codec, rate=RATE)
        stream.width, stream.height, stream.pix_fmt = cols, rows, pix_fmt
        for image in frames:
            if pix_fmt.startswith("yuv"):
                frame = av.VideoFrame.from_ndarray(np.dstack([(image >> 4).astype(np.uint8)] * 3),
                                                   format="rgb24")
            else:
                frame = av.VideoFrame.from_ndarray(image, format=pix_fmt)
            for packet in container.streams.video[0].encode(frame):
                container.mux(packet)
        for packet in container.streams.video[0].encode():
            container.mux(packet)
    return path


def _cut(path: Path, fraction: float, out: Path) -> Path:
    data = path.read_bytes()
    out.write_bytes(data[: int(len(data) * fraction)])
    return out


def _decodable(path: Path) -> int:
    """How many frames FFmpeg itself decodes from ``path`` before it stops or fails."""
    n = 0
    with av.open(str(path)) as container:
        try:
            for _ in container.decode(video=0):
                n += 1
        except av.error.FFmpegError:
            pass
    return n


def _process(source: Path, geometry: Path, out: Path, *extra):
    return _cli("process", source, "--reference-frames", "0:1", "--geometry", geometry, "--out", out,
                "--no-progress", *extra)


def _read(out: Path) -> dict:
    with h5py.File(out, "r") as f:
        return {"status": str(f.attrs["status"]), "expected": int(f.attrs["frames_expected"]),
                "done": int(f.attrs["frames_done"]), "frame_status": f["frame_status"][()],
                "frame_index": f["frame_index"][()], "height": f["height"][()],
                "text": [t.decode() if isinstance(t, bytes) else str(t)
                         for t in f["frame_status_text"][()]]}


@pytest.fixture(scope="module")
def whole_heights(sim128, tmp_path_factory):
    """Heights of the 20 frames processed from the whole (uncut) lossless video."""
    folder, frames = sim128
    d = tmp_path_factory.mktemp("whole")
    path = _write_video(d / "whole.mkv", frames, "ffv1", "gray16le")
    r = _process(path, folder / "geometry.toml", d / "whole.h5")
    assert r.returncode == 0, r.stderr
    return _read(d / "whole.h5")["height"]


@pytest.mark.parametrize("suffix,codec,pix_fmt", [
    (".mkv", "ffv1", "gray16le"),  # no frame count in the container: its duration says 0.8 s
    (".avi", "ffv1", "gray16le"),  # the AVI header's frame count
    (".mov", "png", "gray16be"),  # the sample table (at the front: faststart)
    (".mp4", "libx264", "yuv420p"),  # lossy, at the front too
])
def test_truncated_video_reports_its_missing_frames(sim128, whole_heights, tmp_path, suffix, codec,
                                                    pix_fmt):
    """A video cut to 55 % of its bytes: the container promises 20 frames (0.8 s at 25
    frames/s); the frames FFmpeg still decodes are processed (lossless: the whole
    file's heights exactly), every other one is an UNREADABLE row, frames_expected
    is 20, exit 3."""
    folder, frames = sim128
    whole = _write_video(tmp_path / f"whole{suffix}", frames, codec, pix_fmt)
    cut = _cut(whole, 0.55, tmp_path / f"cut{suffix}")
    decodable = _decodable(cut)
    assert 5 <= decodable < len(frames)  # really cut, and some frames left
    out = tmp_path / "out.h5"
    r = _process(cut, folder / "geometry.toml", out)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    assert "unreadable" in r.stderr and f"{cut}" in r.stderr
    o = _read(out)
    assert o["expected"] == o["done"] == len(frames) == 20
    assert list(o["frame_index"]) == list(range(20))
    assert o["status"] == f"complete, {20 - decodable} frame(s) invalid"
    assert np.all(o["frame_status"][decodable:] == UNREADABLE)
    assert not np.isfinite(o["height"][decodable:]).any()
    assert "missing" in o["text"][-1] or "cannot be decoded" in o["text"][-1]
    kept = o["frame_status"][:decodable] != UNREADABLE
    assert kept.all()
    if codec != "libx264":  # lossless: the frames the cut file holds are measured as from the whole one
        h, w = o["height"][:decodable], whole_heights[:decodable]
        np.testing.assert_array_equal(np.isnan(h), np.isnan(w))
        # float32 sums over a shorter series differ in the last bits (7e-6 of the peak
        # seen); a wrong frame or a 2 pi slip would be percents of it
        assert np.nanmax(np.abs(h - w)) <= 1e-4 * np.nanmax(np.abs(w))


def test_cut_video_gives_the_same_advice_serial_and_in_parallel_chunks(sim128, tmp_path):
    """The FFV1 .avi (its header promises 20 frames) cut to 60 %: over two workers in
    chunks of 4 frames, a chunk that starts past the cut cannot see the frames before it
    missing; it used to advise --frames :16 (its own first frame) where the serial run
    says :N (the first frame the file lacks). Every missing frame's text, and the advice
    in it, must be the serial run's, and N must be the frames FFmpeg decodes."""
    folder, frames = sim128
    cut = _cut(_write_video(tmp_path / "whole.avi", frames, "ffv1", "gray16le"), 0.6, tmp_path / "cut.avi")
    decodable = _decodable(cut)
    assert 4 <= decodable <= len(frames) - 8  # a whole chunk of 4 starts past the cut
    texts = {}
    for workers in ("1", "2"):
        out = tmp_path / f"out{workers}.h5"
        r = _process(cut, folder / "geometry.toml", out, "--workers", workers, "--chunk-frames", "4")
        assert r.returncode == 3, r.stderr
        o = _read(out)
        assert np.all(o["frame_status"][decodable:] == UNREADABLE)
        assert np.all(o["frame_status"][:decodable] != UNREADABLE)
        texts[workers] = o["text"][decodable:]
    advice = {t[t.index("--frames"):] for t in texts["1"] + texts["2"] if "--frames" in t}
    assert advice == {f"--frames :{decodable})"}, advice
    assert texts["2"] == texts["1"]


# --------------------------------------------------------------------------- Phantom CINE


def _cine_with_frames(template: Path, frames, out: Path) -> Path:
    """A copy of the real Phantom file ``template`` (256 x 256, 16-bit words, 15 frames)
    whose images are ``frames``, stored as a Phantom stores them (rows bottom first)."""
    from pims.cine import Cine

    cine = Cine(str(template))
    try:
        locations = list(cine.image_locations)
    finally:
        cine.close()
    data = bytearray(template.read_bytes())
    for location, image in zip(locations, frames):
        annotation = int.from_bytes(data[location:location + 4], "little")
        size = int.from_bytes(data[location + annotation - 4:location + annotation], "little")
        pixels = np.ascontiguousarray(image[::-1]).astype("<u2").tobytes()
        assert len(pixels) == size
        data[location + annotation:location + annotation + size] = pixels
    out.write_bytes(bytes(data))
    return out


@pytest.fixture(scope="module")
def cine_sim(tmp_path_factory):
    pytest.importorskip("pims")
    d = tmp_path_factory.mktemp("cine")
    frames = _simulate(d, 256, 14)  # the reference and 14 frames: the file's 15
    path = _cine_with_frames(CINE_781, frames, d / "sim.cine")
    r = _process(path, d / "geometry.toml", d / "whole.h5")
    assert r.returncode == 0, r.stderr
    return d, path, _read(d / "whole.h5")


@pytest.mark.parametrize("fraction,whole_frames,workers", [(0.6, 8, "1"), (0.6, 8, "2"), (0.95, 14, "1")])
def test_truncated_cine_reports_its_missing_frames(cine_sim, tmp_path, fraction, whole_frames, workers):
    """The CINE cut to 60 % or 95 %: no traceback (PIMS' `cannot reshape array`), the
    frames that are whole are processed (the whole file's heights), the others are
    UNREADABLE rows naming the cut, exit 3, also over two worker processes."""
    d, path, whole = cine_sim
    cut = _cut(path, fraction, tmp_path / "cut.cine")
    out = tmp_path / "out.h5"
    r = _process(cut, d / "geometry.toml", out, "--workers", workers)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr and "reshape" not in r.stderr
    assert "truncated" in r.stderr
    assert out.exists()
    o = _read(out)
    assert o["expected"] == o["done"] == 15
    assert o["status"] == f"complete, {15 - whole_frames} frame(s) invalid"
    assert np.all(o["frame_status"][whole_frames:] == UNREADABLE)
    assert np.all(o["frame_status"][:whole_frames] != UNREADABLE)
    assert f"holds {whole_frames} in full" in o["text"][-1]
    h, w = o["height"][:whole_frames], whole["height"][:whole_frames]
    np.testing.assert_array_equal(np.isnan(h), np.isnan(w))
    peak = np.nanmax(np.abs(w))
    assert peak > 0
    # as tests/app/test_parallel.py: a second process's FFT plans move the image refinement's
    # optimum in cv2.remap's 1/32 px steps; a wrong frame or a 2 pi slip would be ~2 % of the peak
    assert np.nanmax(np.abs(h - w)) <= (1e-4 if workers == "1" else 3e-4) * peak
