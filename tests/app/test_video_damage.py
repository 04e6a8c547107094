"""Damaged, cut and unusual videos and MRAW files, as the by-hand trial of 7 Dec 2026
found them: every file is written here by its own library (PyAV, pyMRAW), then
damaged with bytes zeroed or cut off, as a bad copy does."""

from __future__ import annotations

import math
import re
import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from app.files import formats

av = pytest.importorskip("av")
pyMRAW = pytest.importorskip("pyMRAW")


def _frames(n=16, shape=(64, 64), seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 4096, (n,) + shape).astype(np.uint16)


def _write(path: Path, frames, *, codec="ffv1", rate=500, pix_fmt="gray16le", fmt="gray16le",
           options=None, container_options=None, pts=None, time_base=None) -> Path:
    with av.open(str(path), "w", options=container_options or {}) as container:
        stream = container.add_stream(codec, rate=rate, options=options or {})
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], pix_fmt
        if time_base is not None:
            stream.codec_context.time_base = stream.time_base = time_base
        for k, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(image, format=fmt)
            if pts is not None:
                frame.pts, frame.time_base = pts[k], time_base
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def _packets(path: Path) -> list:
    with av.open(str(path)) as container:
        return [(p.pts, p.pos, p.size, bool(p.is_keyframe)) for p in container.demux() if p.size]


def _zero(path: Path, at: int, n: int) -> None:
    with open(path, "r+b") as f:
        f.seek(at)
        f.write(b"\0" * n)


def _read_all(path: Path, indices=None) -> list:
    with formats.open_source(path) as source:
        return list(source.frames(indices, errors="yield"))


def _errors(items) -> dict:
    return {i: str(image) for i, image, _ in items if isinstance(image, Exception)}


@pytest.mark.parametrize("codec,gop", [("ffvhuff", 1), ("ffv1", 4)])
def test_a_lost_avi_chunk_is_missing_at_its_index_and_later_frames_keep_theirs(tmp_path, codec, gop):
    """By-hand trial of 7 Dec 2026: bytes zeroed in the middle of an FFVHuff / FFV1 AVI
    (the chunk header of frame 5) made the demuxer skip that frame and number every
    later one a frame too early: frames were measured and stored under the wrong index
    and time. Now frame 5 is missing (not called a truncation), the frames after it keep
    their own index and time (FFV1: the frames coded against the lost one, up to the
    next keyframe, are unreadable too), whether read from frame 0 or from frame 8."""
    frames = _frames()
    path = _write(tmp_path / f"{codec}.avi", frames, codec=codec, options={"g": str(gop)})
    pts, pos, size, key = _packets(path)[5]
    _zero(path, pos - 8, 16)  # the chunk's fourcc and size, and the first bytes of its data
    items = _read_all(path)
    assert [i for i, _, _ in items] == list(range(16))
    errors = _errors(items)
    lost = {5} if gop == 1 else {5, 6, 7}  # FFV1: keyframes 0, 4, 8, 12
    assert set(errors) == lost
    assert "frame 5 of" in errors[5] and "missing" in errors[5] and "truncated" not in errors[5]
    for k in lost - {5}:
        assert "frame 5 is damaged or missing" in errors[k] and f"frame {k} of" in errors[k]
    for i, image, time_s in items:
        if i not in lost:
            assert np.array_equal(image, frames[i]), i
            assert time_s == pytest.approx(i / 500), i
    chunk = _read_all(path, range(8, 16))  # as a worker reads its chunk
    assert [i for i, _, _ in chunk] == list(range(8, 16))
    assert all(np.array_equal(image, frames[i]) for i, image, _ in chunk)


def test_a_lost_mkv_cluster_is_missing_at_its_index_and_later_frames_keep_theirs(tmp_path):
    """By-hand trial of 7 Dec 2026: zeroed bytes that took a cluster of an FFV1 MKV (frames
    9..11) made frames 12.. come out as frames 9.., and the file was called truncated with
    its last three frames UNREADABLE. Now frames 9..11 are missing at their own index,
    the file is not called truncated, and the later frames are exact at their times."""
    frames = _frames(24)
    path = _write(tmp_path / "rec.mkv", frames, options={"g": "6"},
                  container_options={"cluster_size_limit": "20000"})
    clusters = [m.start() for m in re.finditer(re.escape(bytes.fromhex("1F43B675")), path.read_bytes())]
    packets = _packets(path)
    lost = [k for k, p in enumerate(packets) if clusters[3] < p[1] < clusters[4]]
    assert lost and lost[-1] + 1 < 24 and packets[lost[-1] + 1][3]  # a keyframe after them
    _zero(path, clusters[3], 32)
    with formats.open_source(path) as source:
        assert source.n_frames == 24 and source.readable_frames is None
        assert not any("truncated" in note for note in source.notes)
    items = _read_all(path)
    errors = _errors(items)
    assert sorted(errors) == lost
    assert all("truncated" not in text for text in errors.values())
    for i, image, time_s in items:
        if i not in errors:
            assert np.array_equal(image, frames[i]) and time_s == pytest.approx(i / 500), i


def test_a_frame_the_decoder_fails_on_costs_that_frame_not_the_rest_of_the_file(tmp_path):
    """By-hand trial of 7 Dec 2026: a packet FFmpeg could not decode ended the file (every
    later frame reported missing, the file called truncated). FFV1 level 3 with slice
    CRCs, bytes zeroed inside frame 5: frame 5 is unreadable (its data are damaged), the
    frames coded against it up to the next keyframe too, and reading goes on from there."""
    frames = _frames(12)
    path = _write(tmp_path / "crc.avi", frames, options={"level": "3", "slicecrc": "1", "g": "4"})
    pts, pos, size, key = _packets(path)[5]
    _zero(path, pos + size // 2, 200)
    items = _read_all(path)
    errors = _errors(items)
    assert sorted(errors) == [5, 6, 7]
    assert "frame 5 of" in errors[5] and "cannot be decoded: its data are damaged" in errors[5]
    for i, image, time_s in items:
        if i not in errors:
            assert np.array_equal(image, frames[i]) and time_s == pytest.approx(i / 500), i


def test_a_5000_fps_mkv_cut_by_four_frames_is_said_truncated_and_timed_by_its_index(tmp_path):
    """By-hand trial of 7 Dec 2026: an FFV1 MKV at 5000 frames/s (1 ms stamps) cut by its
    last four frames was read as whole (exit 0): the duration's tick hid 5 frames. And
    its frames' time_s were the stamps rounded to 1 ms (0, 0, 0, 0.001, ...). Now the cut
    is said (16 frames promised, 12 held) and time_s is index / 5000 s."""
    frames = _frames(16)
    whole = _write(tmp_path / "whole.mkv", frames, rate=5000)
    with formats.open_source(whole) as source:
        assert source.n_frames == 16 and source.readable_frames is None
        times = [t for _, _, t in source.frames()]
        assert any("coarser than its frames" in note for note in source.notes)
    assert times == pytest.approx([k / 5000 for k in range(16)], abs=1e-12)
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(whole.read_bytes()[:_packets(whole)[12][1]])
    with formats.open_source(cut) as source:
        assert source.n_frames == 16 and source.readable_frames == 12
        assert any("truncated" in note for note in source.notes)
        items = list(source.frames(errors="yield"))
    assert sorted(_errors(items)) == [12, 13, 14, 15]


def test_an_intact_variable_rate_mkv_is_not_called_truncated(tmp_path):
    """By-hand trial of 7 Dec 2026: an intact MKV of 16 frames stamped irregularly 0..33 ms
    was called truncated and two phantom UNREADABLE frames were invented."""
    stamps = [0, 2, 4, 7, 8, 10, 15, 16, 18, 20, 25, 26, 28, 30, 31, 33]
    frames = _frames(16)
    path = _write(tmp_path / "vfr.mkv", frames, pts=stamps, time_base=Fraction(1, 1000))
    with formats.open_source(path) as source:
        assert source.n_frames == 16 and source.readable_frames is None
        assert not any("truncated" in note for note in source.notes)
        items = list(source.frames(errors="yield"))
    assert not _errors(items)
    assert [t for _, _, t in items] == pytest.approx([s / 1000 for s in stamps])


def test_time_stamps_going_back_in_an_mkv_are_noted(tmp_path):
    """By-hand trial of 7 Dec 2026: an MKV whose stamps go back by 6 ms at frame 8 (its
    SimpleBlocks' relative stamps patched, as a splice leaves them) was read without a
    word about it."""
    frames = _frames(16)
    path = _write(tmp_path / "back.mkv", frames, pts=list(range(0, 32, 2)), time_base=Fraction(1, 1000),
                  options={"g": "100"})  # one keyframe: one cluster, block stamps from its start
    data = bytearray(path.read_bytes())
    blocks = [p for _, p, _, _ in _packets(path)]  # each SimpleBlock's body
    for k, at in enumerate(blocks):  # body: track vint 0x81, int16 stamp, flags, frame
        assert data[at] == 0x81 and struct.unpack(">h", data[at + 1:at + 3])[0] == 2 * k
        if k >= 8:
            data[at + 1:at + 3] = struct.pack(">h", 2 * k - 6)
    path.write_bytes(bytes(data))
    with formats.open_source(path) as source:
        assert any("go backwards at frame 8" in note for note in source.notes), source.notes
        items = list(source.frames(errors="yield"))
    assert [i for i, _, _ in items] == list(range(16)) and not _errors(items)


def test_16_bit_colour_video_is_read_as_16_bit_grey(tmp_path):
    """By-hand trial of 7 Dec 2026: gbrp16le (rgb48le) FFV1 video was read as 8-bit grey,
    its 12-bit levels crushed to 0..16."""
    frames = _frames(4)
    path = _write(tmp_path / "rgb48.mkv", np.repeat(frames[..., None], 3, axis=3),
                  pix_fmt="gbrp16le", fmt="rgb48le")
    with formats.open_source(path) as source:
        assert source.bits == 16 and source.dtype == np.uint16
        assert any("16-bit grey" in note for note in source.notes)
        images = [image for _, image, _ in source.frames()]
    # FFmpeg's luma of equal R, G, B (full range): the levels within half a percent
    assert all(np.allclose(a, b, rtol=0.006, atol=2) for a, b in zip(images, frames))


@pytest.mark.parametrize("suffix", [".mkv"])
def test_a_video_cut_inside_its_first_frame_is_a_one_line_error(tmp_path, suffix):
    """By-hand trial of 7 Dec 2026: an MKV cut inside its first frame gave only
    "[Errno 1] Operation not permitted" (from a seek)."""
    whole = _write(tmp_path / f"whole{suffix}", _frames(4))
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(whole.read_bytes()[:_packets(whole)[0][1] + 100])
    with pytest.raises(formats.ImageReadError) as err:
        formats.open_source(cut)
    assert str(cut) in str(err.value) and "truncated" in str(err.value)


# --------------------------------------------------------------------------- MRAW


def _mraw(tmp_path: Path, frames, name="rec", bits=16) -> Path:
    _, cih = pyMRAW.save_mraw(np.asarray(frames), str(tmp_path / name), bit_depth=bits,
                              info_dict={"Record Rate(fps)": 5000, "Start Frame": 0})
    return Path(cih)


def _edit(cih: Path, old: str, new: str) -> None:
    text = cih.read_text()
    assert old in text
    cih.write_text(text.replace(old, new))


def test_mraw_longer_than_its_header_says_is_noted(tmp_path):
    """By-hand trial of 7 Dec 2026: a .mraw holding 16 frames whose .cih says
    'Total Frame : 10' was read as 10 frames without a word (the tool's own advice for a
    truncated file is to edit Total Frame)."""
    cih = _mraw(tmp_path, _frames(16))
    _edit(cih, "Total Frame : 16", "Total Frame : 10")
    with formats.open_source(cih) as source:
        assert source.n_frames == 10
        assert any("6 whole frames beyond" in note and "Total Frame : 16" in note
                   for note in source.notes), source.notes


def test_mraw_without_a_frame_rate_says_its_frames_have_no_times(tmp_path):
    """By-hand trial of 7 Dec 2026: 'Record Rate(fps) : 0' gave /time_s NaN with no word."""
    cih = _mraw(tmp_path, _frames(4))
    _edit(cih, "Record Rate(fps) : 5000", "Record Rate(fps) : 0")
    with formats.open_source(cih) as source:
        assert any("gives no frame rate" in note and "/time_s NaN" in note for note in source.notes), source.notes
        assert all(math.isnan(t) for _, _, t in source.frames(range(4)))
    cih = _mraw(tmp_path, _frames(4), name="timed")
    with formats.open_source(cih) as source:
        assert not any("frame rate" in note for note in source.notes), source.notes


@pytest.mark.parametrize("header_bits,data_bits", [(8, 16), (12, 16), (16, 12)])
def test_mraw_header_bit_depth_unlike_the_files_size_is_said_as_such(tmp_path, header_bits, data_bits):
    """By-hand trial of 7 Dec 2026: a .cih whose 'Color Bit' does not fit its .mraw was
    read as garbage (the run then said the pattern did not match) or called truncated."""
    frames = _frames(8)
    cih = _mraw(tmp_path, frames)
    if data_bits == 12:
        cih.with_suffix(".mraw").write_bytes(_pack12(frames))
    text = cih.read_text()
    cih.write_text(re.sub(r"Color Bit : \d+", f"Color Bit : {header_bits}", text))
    with pytest.raises(formats.ImageReadError) as err:
        formats.open_source(cih)
    text = str(err.value)
    assert f"fits 8 frames of {data_bits} bit" in text and "Color Bit" in text and "rec.mraw" in text


def _pack12(samples: np.ndarray) -> bytes:
    a = samples.astype(np.uint16).ravel()
    a = np.concatenate([a, np.zeros(len(a) % 2, np.uint16)])
    p0, p1 = a[0::2], a[1::2]
    b = np.empty((p0.size, 3), np.uint8)
    b[:, 0] = p0 >> 4
    b[:, 1] = ((p0 & 15) << 4) | (p1 >> 8)
    b[:, 2] = p1 & 255
    return b.tobytes()


def test_12_bit_mraw_with_an_odd_pixel_count_is_read_exactly(tmp_path):
    """By-hand trial of 7 Dec 2026: a 12-bit MRAW of 127 x 127 pixels (frames starting in
    the middle of a byte triple) ended in an AssertionError traceback inside pyMRAW."""
    frames = _frames(3, shape=(127, 127))
    cih = _mraw(tmp_path, frames)
    _edit(cih, "Color Bit : 16", "Color Bit : 12")
    cih.with_suffix(".mraw").write_bytes(_pack12(frames))
    with formats.open_source(cih) as source:
        assert source.bits == 12
        images = [image for _, image, _ in source.frames()]
    assert all(np.array_equal(a, b) for a, b in zip(images, frames))
