"""Video (PyAV), Photron MRAW (pyMRAW) and folders of images, read through
``app.files.imageio.iter_frames``; every file here is written by the format's own
library (PyAV encodes the videos, pyMRAW writes the MRAW + CIH)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.files import imageio

av = pytest.importorskip("av")
pyMRAW = pytest.importorskip("pyMRAW")

ROOT = Path(__file__).resolve().parents[2]


def _frames(n=5, shape=(48, 64), hi=4096, seed=0):
    rng = np.random.default_rng(seed)
    dtype = np.uint16 if hi > 256 else np.uint8
    return [rng.integers(0, hi, shape).astype(dtype) for _ in range(n)]


def write_video(path, frames, *, codec="ffv1", pix_fmt="gray16le", rate=250):
    """Encode ``frames`` with PyAV (the container from the suffix)."""
    rows, cols = frames[0].shape
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=rate)
        stream.width, stream.height, stream.pix_fmt = cols, rows, pix_fmt
        for image in frames:
            if pix_fmt.startswith("yuv"):
                frame = av.VideoFrame.from_ndarray(np.dstack([image] * 3), format="rgb24")
            else:
                frame = av.VideoFrame.from_ndarray(image, format=pix_fmt)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def write_mraw(path, frames, *, bits=16, fps=5000, start_frame=0):
    """Photron MRAW + CIH written by pyMRAW; returns the .cih path."""
    _, cih = pyMRAW.save_mraw(np.asarray(frames), str(path), bit_depth=bits,
                              info_dict={"Record Rate(fps)": fps, "Start Frame": start_frame})
    return Path(cih)


# --------------------------------------------------------------------------- video


@pytest.mark.parametrize("suffix,codec,pix_fmt,hi,bits", [
    (".avi", "ffv1", "gray16le", 4096, 16),
    (".avi", "ffv1", "gray12le", 4096, 12),
    (".mkv", "ffv1", "gray", 256, 8),
    (".avi", "rawvideo", "gray", 256, 8),
    (".mov", "png", "gray16be", 65536, 16),
])
def test_lossless_video_reads_exactly(tmp_path, suffix, codec, pix_fmt, hi, bits):
    frames = _frames(hi=hi)
    path = write_video(tmp_path / f"rec{suffix}", frames, codec=codec, pix_fmt=pix_fmt, rate=250)
    info = imageio.image_info(path)
    assert (info.kind, info.n_frames, info.shape, info.bits) == ("video", 5, (48, 64), bits)
    assert info.frame_rate_hz == pytest.approx(250.0)
    assert info.lossless and info.notes == ()
    items = list(imageio.iter_frames([path]))
    assert len(items) == 5
    for k, item in enumerate(items):
        assert np.array_equal(item.image, frames[k]), f"frame {k} differs"
        assert item.time_s == pytest.approx(k / 250.0, abs=1e-9)
    # a frame range decodes to the same frames
    picked = list(imageio.iter_frames([path], first=1, last=4, step=2))
    assert [i.sequence_index for i in picked] == [1, 3]
    assert np.array_equal(picked[1].image, frames[3])
    assert np.array_equal(imageio.read_image(path, index=2), frames[2])


def test_lossy_video_is_read_with_a_warning(tmp_path):
    # smooth pattern, so H.264 keeps it close; a checkerboard would be worse
    y, x = np.mgrid[0:64, 0:96]
    frames = [(128 + 80 * np.sin(2 * np.pi * (x + k) / 16) * np.sin(2 * np.pi * y / 16)).astype(np.uint8)
              for k in range(4)]
    path = write_video(tmp_path / "talk.mp4", frames, codec="libx264", pix_fmt="yuv420p", rate=30)
    info = imageio.image_info(path)
    assert not info.lossless and info.codec == "h264"
    notes = imageio.input_notes([path])
    assert "lossy" in notes[0] and "Fourier demodulation" in notes[0]
    items = list(imageio.iter_frames([path]))
    assert len(items) == 4 and items[0].image.dtype == np.uint8
    # the grey (luma) of what was encoded, within H.264 artefacts at default quality
    err = np.abs(items[2].image.astype(float) - frames[2])
    assert np.median(err) <= 4
    # starting late seeks (to the keyframe before, by time stamp) and gives the same frames
    late = list(imageio.iter_frames([path], first=2))
    assert [i.sequence_index for i in late] == [2, 3]
    assert all(np.array_equal(a.image, items[a.sequence_index].image) for a in late)


def _read(source, indices):
    return [(i, image) for i, image, _ in source.frames(indices)]


@pytest.mark.parametrize("suffix,gop", [(".avi", 3), (".mkv", 3), (".avi", 1)])
def test_video_random_access_is_exact(tmp_path, suffix, gop):
    """FFV1 with a keyframe every ``gop`` frames (AVI: the index from the file's idx1;
    MKV: from one pass over the packets): frames read in order, with a step, and out
    of order from one open file are the frames written, with their own time stamps."""
    from app.files import formats

    frames = _frames(n=20, shape=(32, 40))
    path = tmp_path / f"rec{suffix}"
    rows, cols = frames[0].shape
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=100)
        stream.width, stream.height, stream.pix_fmt = cols, rows, "gray16le"
        stream.codec_context.gop_size = gop
        for image in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="gray16le")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    with av.open(str(path)) as container:  # what the encoder made keyframes
        keys = [k for k, p in enumerate(p for p in container.demux() if p.size) if p.is_keyframe]
    assert keys == list(range(0, 20, gop))
    with formats.open_source(path) as source:
        assert source.n_frames == 20
        for indices in (range(20), range(0, 20, 4), range(13, 17), range(2, 20, 7), range(0, 1),
                        range(19, 20), range(5, 6), range(1, 20, 3)):
            got = _read(source, indices)
            assert [i for i, _ in got] == list(indices), indices
            for i, image in got:
                assert np.array_equal(image, frames[i]), (indices, i)
        times = [t for _, _, t in source.frames(range(3, 20, 5))]
        assert times == pytest.approx([0.03, 0.08, 0.13, 0.18], abs=1e-12)
        # reading stopped half-way (a consumer leaving the loop), then elsewhere
        partial = source.frames(range(20))
        assert next(partial)[0] == 0
        partial.close()
        assert np.array_equal(_read(source, range(18, 19))[0][1], frames[18])
    # the same through the one reader, as `--frames 2:17:5` asks
    items = list(imageio.iter_frames([path], first=2, last=16, step=5))
    assert [item.sequence_index for item in items] == [2, 7, 12]
    assert all(np.array_equal(item.image, frames[item.sequence_index]) for item in items)


def test_video_packet_index_skips_what_a_step_does_not_need():
    """Which frames a strided read decodes: from the keyframe at or before each wanted
    frame up to it, nothing else (keyframes every 4 frames)."""
    from app.files.formats import _PacketIndex

    index = _PacketIndex(tuple(range(0, 200, 10)), (0, 4, 8, 12, 16), True)
    assert index.frame_of[30] == 3 and index.keyframe_before(7) == 4
    decoded = [k for k in range(20) if index.needed(k, range(2, 20, 6))]  # wants 2, 8, 14
    assert decoded == [0, 1, 2, 8, 12, 13, 14]
    assert [k for k in range(20) if index.needed(k, range(5, 20))] == list(range(4, 20))
    intra = _PacketIndex(tuple(range(20)), tuple(range(20)), True)
    assert [k for k in range(20) if intra.needed(k, range(1, 20, 4))] == [1, 5, 9, 13, 17]


# --------------------------------------------------------------------------- Photron MRAW


@pytest.mark.parametrize("bits,hi", [(8, 256), (16, 4096)])
def test_mraw_frames_rate_and_trigger(tmp_path, bits, hi):
    frames = _frames(n=6, hi=hi)
    cih = write_mraw(tmp_path / "shot" / "shot.cih", frames, bits=bits, fps=5000, start_frame=-2)
    for path in (cih, cih.with_suffix(".mraw"), cih.parent):  # header, data file, folder
        items = list(imageio.iter_frames([path]))
        assert len(items) == 6
        for k, item in enumerate(items):
            assert np.array_equal(item.image, frames[k])
            # Start Frame -2: the trigger is frame 2 of the file, at t = 0
            assert item.time_s == pytest.approx((k - 2) / 5000.0, abs=1e-12)
    info = imageio.image_info(cih)
    assert (info.kind, info.n_frames, info.shape) == ("mraw", 6, (48, 64))
    assert info.frame_rate_hz == 5000.0 and info.trigger_index == 2
    assert info.bits == (8 if bits == 8 else 12)  # pyMRAW writes EffectiveBit Depth 12 for 16 bit
    assert np.array_equal(imageio.read_image(cih, index=5), frames[5])


@pytest.mark.parametrize("bits,hi", [(8, 256), (16, 4096)])
def test_mraw_random_access_is_exact(tmp_path, bits, hi):
    """A pyMRAW-written MRAW read in order, with a step and out of order from one open
    file: the frames written, each with its own time."""
    from app.files import formats

    frames = _frames(n=12, shape=(24, 40), hi=hi, seed=3)
    cih = write_mraw(tmp_path / "shot.cih", frames, bits=bits, fps=2000, start_frame=-4)
    with formats.open_source(cih) as source:
        for indices in (range(12), range(0, 12, 5), range(9, 12), range(1, 12, 4), range(6, 7), range(0, 1)):
            got = list(source.frames(indices))
            assert [i for i, _, _ in got] == list(indices)
            for i, image, time_s in got:
                assert np.array_equal(image, frames[i]), (indices, i)
                assert time_s == pytest.approx((i - 4) / 2000.0, abs=1e-12)


PHOTRON = Path(__file__).parent / "data" / "photron"


@pytest.mark.parametrize("name,n,shape,bits,fps,start", [
    ("beam", 4, (80, 1024), 12, 50000.0, 0),         # 16-bit storage, 12 significant bits
    ("ball_12bit", 15, (384, 384), 12, 30000.0, 52),  # packed 12 bit
])
def test_real_photron_cihx_recordings(name, n, shape, bits, fps, start):
    """Real PFV recordings (CIHX headers): frames read one at a time equal pyMRAW's own
    whole-file decoder; rate, depth and the start frame come from the header."""
    header = PHOTRON / f"{name}.cihx"
    expected, _ = pyMRAW.load_video(str(header))
    info = imageio.image_info(header)
    assert (info.n_frames, info.shape, info.bits, info.frame_rate_hz) == (n, shape, bits, fps)
    assert info.trigger_index == (0 if start == 0 else None)  # frame 52 on: trigger not in the file
    items = list(imageio.iter_frames([header], first=1, step=2))
    assert [i.sequence_index for i in items] == list(range(1, n, 2))
    for item in items:
        assert np.array_equal(item.image, expected[item.sequence_index])
        assert item.time_s == pytest.approx((start + item.sequence_index) / fps, abs=1e-12)
    assert int(expected.max()) <= 2 ** bits - 1


def test_truncated_mraw_is_one_line_error(tmp_path):
    cih = write_mraw(tmp_path / "cut.cih", _frames(n=4), bits=16)
    data = cih.with_suffix(".mraw")
    data.write_bytes(data.read_bytes()[: 48 * 64 * 2 * 2 + 100])
    with pytest.raises(imageio.ImageReadError, match=r"2 complete.*truncated"):
        imageio.frame_count(cih)


# --------------------------------------------------------------------------- folders, globs, ranges


def test_folder_and_glob_in_natural_order(tmp_path):
    frames = _frames(n=12, hi=256)
    for k, image in enumerate(frames):
        imageio.write_image(tmp_path / f"frame_{k}.png", image)
    by_folder = imageio.expand_inputs([tmp_path])
    assert [Path(p).name for p in by_folder[:4]] == ["frame_0.png", "frame_1.png", "frame_2.png", "frame_3.png"]
    assert Path(by_folder[10]).name == "frame_10.png"
    assert imageio.expand_inputs([str(tmp_path / "frame_*.png")]) == by_folder
    items = list(imageio.iter_frames([tmp_path], first=2, last=10, step=8))
    assert [Path(i.source).name for i in items] == ["frame_2.png", "frame_10.png"]
    assert np.array_equal(items[1].image, frames[10])
    assert math.isnan(items[0].time_s)


def test_frame_range_parsing():
    assert imageio.parse_frame_range("0:20") == slice(0, 20, None)
    assert imageio.parse_frame_range("100::2") == slice(100, None, 2)
    assert range(50)[imageio.parse_frame_range("-10:")] == range(40, 50)
    with pytest.raises(imageio.ImageReadError, match="START:STOP:STEP"):
        imageio.parse_frame_range("a:b")
    with pytest.raises(imageio.ImageReadError, match="step"):
        imageio.parse_frame_range("0:10:0")
    # `--frames -100:` (the last 100 frames) reaches argparse as one value, not as an option
    from app.cli.main import build_parser, _join_negative_pairs

    argv = _join_negative_pairs(["process", "ref.tif", "rec.avi", "--frames", "-100:", "--out", "o.h5"])
    args = build_parser().parse_args(argv)
    assert args.frame_range == slice(-100, None, None) and args.frames == ["rec.avi"]


# --------------------------------------------------------------------------- same heights from every format


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def sim12(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim12")
    r = _cli("simulate", "--out", out, "--surface", "waves", "--size", "128", "--frames", "4",
             "--bits", "12", "--noise", "1.0", "--overwrite")
    assert r.returncode == 0, r.stderr
    return out


def test_same_heights_from_tiff_folder_avi_and_mraw(sim12, tmp_path):
    """The reference and 4 frames of a 12-bit simulation stored as a TIFF folder, a
    lossless FFV1 AVI and a 16-bit MRAW give the same heights: the readers add nothing."""
    reference = imageio.read_image(sim12 / "reference.tif")
    frames = [imageio.read_image(sim12 / f"frame_{k:04d}.tif") for k in range(4)]
    folder = tmp_path / "tiffs"
    folder.mkdir()
    for k, image in enumerate([reference, *frames]):
        imageio.write_image(folder / f"img_{k}.tif", image)  # natural order: img_0 = reference
    avi = write_video(tmp_path / "rec.avi", [reference, *frames], rate=1000)
    cih = write_mraw(tmp_path / "rec.cih", [reference, *frames], bits=16, fps=1000)
    outputs = {}
    for name, source in (("tiff", folder), ("avi", avi), ("mraw", cih)):
        out = tmp_path / f"{name}.h5"
        r = _cli("process", source, "--reference-frames", "0:1", "--frames", "1:",
                 "--geometry", sim12 / "geometry.toml", "--out", out, "--no-progress")
        assert r.returncode == 0, r.stderr
        with h5py.File(out, "r") as f:
            outputs[name] = (f["height"][()], f["frame_index"][()], f["time_s"][()])
    h_tiff, index, _ = outputs["tiff"]
    assert h_tiff.shape == (4, 128, 128) and list(index) == [1, 2, 3, 4]
    peak = np.nanmax(np.abs(h_tiff))
    assert peak > 1e-4  # micrometres of waves, really measured
    for name in ("avi", "mraw"):
        h, idx, time_s = outputs[name]
        assert list(idx) == [1, 2, 3, 4]
        np.testing.assert_array_equal(np.isnan(h), np.isnan(h_tiff))
        assert np.nanmax(np.abs(h - h_tiff)) <= 1e-6 * peak, name
        assert time_s == pytest.approx(np.arange(1, 5) / 1000.0, abs=1e-9)
    assert np.all(np.isnan(outputs["tiff"][2]))  # image files carry no time


def test_reference_frames_of_an_8_bit_mraw_are_judged_saturated_at_its_top_code(sim12, tmp_path):
    """--reference-frames 0:1 of an 8-bit MRAW whose bright squares peak at one level below
    255 (many pixels at that level): not saturated, as the same image given as the reference
    file is not; the same frames over-exposed (clipped at 255) are said saturated."""
    images = [imageio.read_image(sim12 / "reference.tif")]
    images += [imageio.read_image(sim12 / f"frame_{k:04d}.tif") for k in range(4)]
    counts = [(np.asarray(image) >> 4).astype(np.uint8) for image in images]
    top = int(counts[0].max())
    assert top < 250 and np.mean(counts[0] == top) > 0.01  # a level many pixels share, far from 255
    said = {}
    for name, scale in (("exposed", 1.0), ("over", 1.6)):
        frames = [np.clip(c * scale, 0, 255).astype(np.uint8) for c in counts]
        cih = write_mraw(tmp_path / name / "rec.cih", frames, bits=8, fps=1000)
        out = tmp_path / f"{name}.h5"
        r = _cli("process", cih, "--reference-frames", "0:1", "--frames", "1:", "--workers", "1",
                 "--geometry", sim12 / "geometry.toml", "--out", out, "--no-progress")
        assert r.returncode == 0, r.stderr
        with h5py.File(out, "r") as f:
            said[name] = (float(f.attrs["reference_saturated_pct"]), "saturated" in r.stderr)
            assert list(f["frame_index"][()]) == [1, 2, 3, 4]
    assert said["exposed"] == (0.0, False)
    assert said["over"][0] > 1.0 and said["over"][1]


def test_workers_on_a_video_with_keyframes_give_serial_heights(sim12, tmp_path):
    """`process --workers 2` on an FFV1 AVI with a keyframe every 4 frames: chunks
    end on keyframes, each worker decodes from its own, and the heights are those
    of one process reading the file from start to end."""
    reference = imageio.read_image(sim12 / "reference.tif")
    frames = [imageio.read_image(sim12 / f"frame_{k:04d}.tif") for k in range(4)]
    path = tmp_path / "rec.avi"
    sequence = [reference] + frames * 6  # 25 frames: three chunks of 8 at 2 workers
    rows, cols = reference.shape
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=1000)
        stream.width, stream.height, stream.pix_fmt = cols, rows, "gray16le"
        stream.codec_context.gop_size = 4
        for image in sequence:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="gray16le")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    heights = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}.h5"
        r = _cli("process", path, "--reference-frames", "0:1", "--frames", "1:", "--workers", workers,
                 "--geometry", sim12 / "geometry.toml", "--out", out, "--no-progress")
        assert r.returncode == 0, r.stderr
        with h5py.File(out, "r") as f:
            heights[workers] = (f["height"][()], f["frame_index"][()])
    (h1, i1), (h2, i2) = heights["1"], heights["2"]
    assert list(i1) == list(i2) == list(range(1, 25))
    peak = np.nanmax(np.abs(h1))
    np.testing.assert_array_equal(np.isnan(h1), np.isnan(h2))
    # as tests/app/test_parallel.py: the image refinement's optimum moves in cv2.remap's
    # 1/32 px steps between FFT plans; a wrong frame or a 2 pi slip would be ~2 % of the peak
    assert np.nanmax(np.abs(h1 - h2)) <= 3e-4 * peak


# --------------------------------------------------------------------------- Phantom CINE (a real sample file)

CINE_SAMPLE = Path(__file__).parent / "data" / "cine" / "chart1.cine"


def test_cine_header_of_a_real_phantom_file():
    pytest.importorskip("pims")
    info = imageio.image_info(CINE_SAMPLE)
    assert (info.kind, info.n_frames, info.shape) == ("cine", 1, (1080, 2048))
    assert info.bits == 10 and info.frame_rate_hz == 25.0
    assert info.trigger_index is None  # first image -123: the trigger frame is not in the file
    assert "colour" in info.codec and info.notes


CINE_DATA = Path(__file__).parent / "data" / "cine"


@pytest.mark.parametrize("name,n,shape,bits,frame_interval_s,header_hz,ffmpeg_upside_down", [
    # PCC 3.3.781: recorded at 90,000 frames/s, saved 1 in 10 (PIMS' notes on the file);
    # its setup has bFlipV set, which FFmpeg alone applies to the stored rows
    ("cine_781", 15, (256, 256), 12, 10 / 90000, 90000.0, True),
    ("cine_legacy", 97, (128, 128), 14, 1 / 35087, 35087.0, False),  # PCC of 2008
])
def test_real_monochrome_phantom_cine(name, n, shape, bits, frame_interval_s, header_hz,
                                      ffmpeg_upside_down):
    """Real monochrome Phantom files: every frame, read in order, alone or with a step,
    equals FFmpeg's own CINE demuxer's (an independent reader, which fills samples out
    to 16 bits by bit replication); the depth is the header's; the per-frame times are the camera's
    stamps, at the rate the frames were saved at, and agree with the header's first
    image number."""
    pytest.importorskip("pims")
    import av

    from app.files import formats

    path = CINE_DATA / f"{name}.cine"
    info = imageio.image_info(path)
    assert (info.kind, info.n_frames, info.shape, info.dtype, info.bits) == ("cine", n, shape, np.uint16, bits)
    with av.open(str(path)) as container:
        ffmpeg = [f.to_ndarray() for f in container.decode(video=0)]
    assert len(ffmpeg) == n
    with formats.open_source(path) as source:
        for indices in (range(n), range(n - 1, n), range(1, n, 3), range(0, 1)):
            for i, image, _ in source.frames(indices):
                assert image.dtype == np.uint16 and int(image.max()) <= 2 ** bits - 1
                wide = image.astype(np.uint32)
                as_ffmpeg = (wide << (16 - bits)) | (wide >> (2 * bits - 16))
                expected = ffmpeg[i][::-1] if ffmpeg_upside_down else ffmpeg[i]
                assert np.array_equal(as_ffmpeg, expected), (indices, i)
    items = list(imageio.iter_frames([path]))
    times = np.array([item.time_s for item in items])
    intervals = np.diff(times)
    # the camera stamps each frame to 1 us or better: every interval within 1.1 us of the
    # saved frames' spacing, and the mean within 0.1 % of it (not the header's 90,000/s)
    assert np.all(np.abs(intervals - frame_interval_s) < 1.1e-6), intervals
    assert np.mean(intervals) == pytest.approx(frame_interval_s, rel=1e-3)
    assert info.frame_rate_hz == pytest.approx(1 / frame_interval_s, rel=1e-3)
    assert bool(info.notes) == (info.frame_rate_hz < 0.5 * header_hz)  # the saving step is said
    # both were triggered after their last frame: every time is negative, no trigger index,
    # and the first frame's time is its image number (counted in saved frames) over the
    # rate, to within a frame and a half (0.2 and 1.2 frames here: a stamp may mark the
    # end of an exposure, the image number its start)
    first_image_no = {"cine_781": -5417, "cine_legacy": -7722}[name]
    assert info.trigger_index is None and times[-1] < 0
    assert abs(times[0] - first_image_no / info.frame_rate_hz) < 1.5 * frame_interval_s


def test_cine_frames_are_upright():
    """Rows come out top first, as PCC shows them (PIMS and pycine read the stored rows
    bottom-up, whatever bFlipV says; FFmpeg turns a file with bFlipV over). Gravity
    decides: in cine_781 gas bubbles rise from a needle below them, so the dark needle
    crosses the picture's bottom edge and nothing dark touches its top edge."""
    pytest.importorskip("pims")
    items = list(imageio.iter_frames([CINE_DATA / "cine_781.cine"], step=7))
    for item in items:
        background = float(np.median(item.image))
        assert item.image[-4:].min() < 0.1 * background  # the needle, at 3 % of the background
        assert item.image[:4].min() > 0.8 * background


def test_colour_cine_is_refused_in_one_line(tmp_path):
    pytest.importorskip("pims")
    r = _cli("process", CINE_SAMPLE, CINE_SAMPLE, "--geometry", ROOT / "tests" / "app" / "data"
             / "cine" / "missing.toml", "--out", tmp_path / "o.h5")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    with pytest.raises(imageio.ImageReadError, match="colour recording.*monochrome"):
        next(imageio.iter_frames([CINE_SAMPLE]))
    assert not (tmp_path / "o.h5").exists()


# --------------------------------------------------------------------------- Replay opens them


def test_replay_opens_mraw_and_video(tmp_path, qtbot):
    """The Replay tab's Recording reads camera files and videos frame by frame, any order,
    with trigger-relative indices from the Photron header."""
    from app.gui.replay import RECORDING_FILTER, Recording, ReplayTab

    frames = _frames(n=6, hi=4096)
    cih = write_mraw(tmp_path / "shot.cih", frames, bits=16, fps=2000, start_frame=-2)
    avi = write_video(tmp_path / "shot.avi", frames, rate=1000)
    tab = ReplayTab()
    qtbot.addWidget(tab)
    for path in (cih, avi):
        assert f"*{path.suffix}" in RECORDING_FILTER
        rec = Recording(str(path))
        try:
            assert rec.n_frames == 6 and rec.reference is None
            for k in (0, 1, 2, 5, 3, 4):  # forwards, backwards, jumps
                assert np.array_equal(rec.frame(k), frames[k])
            assert rec.trigger_index(0) == (-2 if path == cih else None)
            tab.set_recording(rec)
            assert tab.slider.maximum() == 5 and tab.export_button.isEnabled()
            assert "6 frames" in tab.file_label.text()
        finally:
            rec.close()


def test_frame_range_errors_are_one_line(tmp_path):
    cih = write_mraw(tmp_path / "r.cih", _frames(n=4), bits=16)
    geometry = tmp_path / "g.toml"
    geometry.write_text('setup = "tir"\ntheta_deg = 55.0\ndepth_mm = 300.0\npixel_mm = 0.1\n'
                        'rows_toward_camera = false\n')
    for extra, needle in ((["--frames", "1:", "--first", "2"], "not both"),
                          (["--frames", "10:20"], "selects no frame of the 4"),
                          (["--frames", "1:2:0"], "step"),
                          (["--reference-frames", "5:9"], "select no frame")):
        r = _cli("process", cih, "--geometry", geometry, "--out", tmp_path / "o.h5",
                 *(["--reference-frames", "0:1"] if "--reference-frames" not in extra else []), *extra)
        assert r.returncode == 2, (extra, r.stderr)
        assert r.stderr.count("\n") <= 1 or "usage:" in r.stderr, r.stderr
        assert needle in r.stderr, (needle, r.stderr)
        assert not (tmp_path / "o.h5").exists()
