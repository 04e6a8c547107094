"""High-speed camera files and video, each read through its own well-kept library.

:mod:`app.files.imageio` dispatches to these for the formats below; nothing
else should import this module (``imageio.iter_frames`` is the one reader).

============  =====================================  ============================
kind          files                                  library
============  =====================================  ============================
``video``     .avi .mkv .mp4 .mov .m4v .webm          PyAV (``av``, FFmpeg)
``mraw``      Photron .cih / .cihx + .mraw           pyMRAW (header, 12-bit unpacking)
``cine``      Phantom .cine                          PIMS (``pims.cine.Cine``)
============  =====================================  ============================

Each opens as a :class:`Source`: frame count, shape, dtype, significant bits,
frame rate, the index of the trigger frame when the file says it, and
:meth:`Source.frames` yielding ``(index, image, time_s)`` lazily (one frame
decoded at a time; MRAW and CINE seek; video seeks to the keyframe before the
first frame wanted, then decodes forward, ahead in a thread). ``time_s`` is
the frame's time in seconds: relative to the trigger for MRAW and CINE (the
Phantom's per-frame time stamps, which also give the rate of a file saved
with a step; Photron: ``(start frame + i) / rate``), the presentation time
stamp for video.

Values are unscaled, as in :mod:`app.files.imageio`: a 12-bit Photron MRAW
gives uint16 in 0..4095 (``bits`` 12), a ``gray12le`` FFV1 video likewise.
Lossy video (H.264, MJPEG, MPEG-4, ...) is read, but :attr:`Source.notes`
says that compression artefacts bias Fourier demodulation.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from processing.errors import TirdeflectError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = frozenset({".avi", ".mkv", ".mp4", ".mov", ".m4v", ".webm"})
MRAW_SUFFIXES = frozenset({".cih", ".cihx", ".mraw"})
CINE_SUFFIXES = frozenset({".cine"})

#: Codecs that store every sample exactly (a frame decodes to what was encoded).
LOSSLESS_CODECS = frozenset({
    "ffv1", "rawvideo", "png", "apng", "huffyuv", "ffvhuff", "utvideo", "magicyuv",
    "qtrle", "tiff", "zlib", "zmbv", "lagarith", "v210", "v410", "r210", "y41p", "yuv4",
    "jpegls", "bmp", "gif",
})



class ImageReadError(TirdeflectError):
    """An input file is missing, unreadable or not a single-channel image (the message
    names the file, the problem and what to do). Re-exported by :mod:`app.files.imageio`."""


#: The name used in this module.
FormatError = ImageReadError


@dataclass(frozen=True)
class ImageInfo:
    """What an input file holds, without reading its pixels.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    kind : str
        ``"image"`` (PNG/BMP/JPEG), ``"tiff"``, ``"recording"`` (HDF5), ``"video"``,
        ``"mraw"`` or ``"cine"``.
    n_frames : int
        Number of frames: 1 for a plain image, the page count of a TIFF
        stack, the length of ``/frames`` of a recording.
    shape : tuple of int
        ``(rows, cols)`` of one frame, in pixels.
    dtype : numpy.dtype
        Sample type as returned by :func:`read_image` / :func:`iter_frames`.
    bits : int
        Significant bits per sample (10 for a packed 10-bit TIFF); for float
        images the bit width of the float.
    frame_rate_hz : float
        Frame rate of the frames in the file (video, MRAW, CINE; for a CINE saved
        with a step, from its time stamps, not its header's recording rate); NaN
        otherwise.
    trigger_index : int or None
        Index of the trigger frame in the file (MRAW, CINE), when stated.
    codec : str
        Video codec or camera file layout ("" for images and recordings).
    lossless : bool
        False for lossy video codecs.
    notes : tuple of str
        Warnings about the file (lossy codec...).
    """

    path: Path
    kind: str
    n_frames: int
    shape: tuple
    dtype: np.dtype
    bits: int
    frame_rate_hz: float = math.nan
    trigger_index: int | None = None
    codec: str = ""
    lossless: bool = True
    notes: tuple = ()


@dataclass(frozen=True)
class Source(ImageInfo):
    """One opened multi-frame file (see the module docstring): what
    :class:`ImageInfo` says of it (``kind`` ``"video"``, ``"mraw"`` or
    ``"cine"``; ``notes`` such as a lossy codec or colour converted to luma),
    and its frames.

    Attributes
    ----------
    time_origin : str
        What ``time_s`` is counted from: ``"trigger"`` or ``"stream start"``.
    readable_frames : int or None
        How many of the ``n_frames`` the header promises the file holds, where that
        is known at open and fewer (a truncated file: the frames past them are
        reported missing, see :meth:`frames`); None otherwise.
    """

    time_origin: str = "stream start"
    readable_frames: int | None = None
    _frames: object = None
    _close: object = None
    _keyframes: object = None
    _closed: list = field(default_factory=list, repr=False, compare=False)

    def info(self) -> ImageInfo:
        """The file's description alone (no open file behind it)."""
        return ImageInfo(**{f.name: getattr(self, f.name) for f in dataclasses.fields(ImageInfo)})

    def frames(self, indices: range | None = None, errors: str = "raise") -> Iterator[tuple]:
        """Yield ``(index, image, time_s)`` for the frames of ``indices`` (an increasing
        ``range``; default all), decoding only those (video also decodes the frames
        from the keyframe before each wanted one, without converting them).

        Every index of ``indices`` is accounted for: a frame the file's header
        promises but that cannot be read (the file ends before it, its decoder
        fails or skips it) raises its :class:`ImageReadError` (``errors="raise"``),
        or is yielded as ``(index, error, nan)`` (``errors="yield"``; the frames
        after it follow, each readable one or its own error)."""
        indices = range(self.n_frames) if indices is None else indices
        return _accounted(self._frames(indices), indices, self, errors)

    def keyframes(self) -> tuple | None:
        """The frames a decoder can start at, increasing (video: its keyframes;
        reading from any other frame decodes from the keyframe before it), or
        None where every frame can be read on its own (MRAW, CINE) or the
        video's packets do not say (no distinct time stamps)."""
        keys = None if self._keyframes is None else self._keyframes()
        return None if keys is None else tuple(keys)

    def close(self) -> None:
        if self._close is not None and not self._closed:
            self._closed.append(True)
            self._close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _accounted(frames: Iterator[tuple], indices: range, source: Source, errors: str) -> Iterator[tuple]:
    """The items of a reader's ``frames`` for ``indices``, with each wanted index that
    it skipped, or did not reach before it ended or failed, as an ImageReadError
    (raised, or yielded as ``(index, error, nan)``; see :meth:`Source.frames`)."""
    if errors not in ("raise", "yield"):
        raise ValueError(f"errors must be 'raise' or 'yield'; got {errors!r}")
    wanted = iter(indices)
    pending = next(wanted, None)
    failure = None  # (index, the decoder's own error): said for the frame it failed at
    first_missing: list = []

    def missing(i: int, later: int | None = None):
        if later is not None:  # the reader went on to frame ``later``: a damaged stretch, not a cut
            return FormatError(
                f"frame {i} of {str(source.path)!r} is missing: the reader found no intact data "
                f"for it (a damaged stretch of the file; frame {later} after it was read, each "
                f"frame at its own index and time): copy the file again from its source if you "
                f"need this frame")
        first_missing[:] = first_missing or [i]
        known = source.readable_frames
        if failure is not None and i == failure[0] and (known is None or i < known):
            return failure[1]  # the decoder's own words (not for a frame known to be cut off)
        # the advice names the first frame the file lacks: known at open (readable_frames),
        # else the first this reader missed (a later chunk cannot see the frames before it)
        before = known if known is not None else first_missing[0]
        return FormatError(
            f"frame {i} of {str(source.path)!r} is missing: the file's header promises "
            f"{source.n_frames} frames but {_readable_text(source, failure)}; the file is "
            f"truncated (an interrupted copy or recording): copy it again from its source, "
            f"or process the frames before it (--frames :{before})")

    try:
        try:
            for item in frames:
                i = item[0]
                while pending is not None and pending < i:  # skipped by the decoder
                    yield from _missing_item(missing(pending, i), pending, errors)
                    pending = next(wanted, None)
                if pending is not None and pending == i:
                    if isinstance(item[1], Exception):
                        yield from _missing_item(item[1], i, errors)
                    else:
                        yield item
                    pending = next(wanted, None)
        except FormatError as exc:  # a decoder cannot go on past a frame it fails at
            failure = (pending, exc)
        while pending is not None:
            yield from _missing_item(missing(pending), pending, errors)
            pending = next(wanted, None)
    finally:  # leaving early stops the reader (a video's decoding thread) now, not at collection
        close = getattr(frames, "close", None)
        if close is not None:
            close()


def _span(first: int, n: int) -> str:
    """``frame 9 is`` or ``frames 9..14 are``."""
    return f"frame {first} is" if n - first == 1 else f"frames {first}..{n - 1} are"


def _missing_item(error: FormatError, i: int, errors: str):
    if errors == "raise":
        error.index_in_source = i  # the frame it is about (the reader had yielded up to before it)
        raise error
    yield i, error, math.nan


def _readable_text(source: Source, failure) -> str:
    if source.readable_frames is not None:
        return f"it holds only the first {source.readable_frames} in full"
    if failure is not None:
        return f"decoding failed at frame {failure[0]}"
    return "decoding ended before this one"


def kind_of(path: Path) -> str | None:
    """``"video"``, ``"mraw"``, ``"cine"`` from the file name, else None."""
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return "video"
    if suffix in MRAW_SUFFIXES:
        return "mraw"
    if suffix in CINE_SUFFIXES:
        return "cine"
    return None


def open_source(path: Path) -> Source:
    """Open ``path`` (kind from its suffix, :func:`kind_of`) as a :class:`Source`."""
    kind = kind_of(path)
    if kind == "video":
        return _open_video(path)
    if kind == "mraw":
        return _open_mraw(path)
    if kind == "cine":
        return _open_cine(path)
    raise FormatError(f"{str(path)!r} is not a video, Photron or Phantom file")


def _missing(library: str, package: str, what: str) -> FormatError:
    return FormatError(
        f"reading {what} needs the Python package {package!r} ({library}), which is not "
        f"installed; run `pip install {package}` (or `pip install tirdeflect[formats]`)"
    )


# =========================================================================== video (PyAV)


def _bits_of_pix_fmt(name: str) -> int:
    """Significant bits of one sample of pixel format ``name`` (its deepest component:
    16 for ``gbrp16le`` and ``rgb48le``, 10 for ``yuv420p10le``), from FFmpeg's own
    description of the format; 8 where it is unknown."""
    try:
        import av

        return max(int(c.bits) for c in av.VideoFormat(name).components)
    except Exception:  # an unknown or empty name
        m = re.search(r"(\d+)(le|be)$", name)
        if m and name.startswith(("gray", "yuv", "p0")):
            return int(m.group(1))
        return 8


def _video_plane0(frame, bits: int) -> np.ndarray:
    """The grey (or luma) plane of a decoded frame, unscaled, without a colour conversion."""
    plane = frame.planes[0]
    rows, cols = frame.height, frame.width
    dtype = np.dtype("<u2") if bits > 8 else np.dtype(np.uint8)
    stride = plane.line_size // dtype.itemsize
    arr = np.frombuffer(plane, dtype=dtype).reshape(-1, stride)[:rows, :cols]
    return np.ascontiguousarray(arr).astype(np.uint16 if bits > 8 else np.uint8, copy=False)


class _Unindexed(Exception):
    """A packet or frame whose time stamp the packet index does not know."""


@dataclass(frozen=True)
class _PacketIndex:
    """Where each frame of a video stream is: ``pts[k]`` is frame k's presentation time
    stamp (frames in presentation order), ``keyframes`` the frames a decoder can start
    at (always including 0), ``in_decode_order`` whether the packets come in that same
    order (no reordered B-frames)."""

    pts: tuple
    keyframes: tuple
    in_decode_order: bool
    #: byte position of each frame's packet -> frame index, where the container's own
    #: index lists it (AVI idx1: its demuxer numbers the packets it finds, so that a
    #: packet lost to damage would shift every later packet's stamp); else None
    pos_of: dict | None = field(default=None, repr=False, compare=False)

    frame_of: dict = field(init=False, repr=False, compare=False)  # stamp -> frame index

    def __post_init__(self):
        object.__setattr__(self, "frame_of", {t: k for k, t in enumerate(self.pts)})

    def keyframe_before(self, k: int) -> int:
        """The last keyframe at or before frame ``k``."""
        return self.keyframes[max(0, bisect.bisect_right(self.keyframes, k) - 1)]

    def needed(self, k: int, wanted: range) -> bool:
        """Whether frame ``k`` must be decoded to get the frames of ``wanted`` (packets in
        decode order): it is wanted, or no keyframe lies between it and the next wanted frame."""
        if k >= wanted.stop:
            return False
        j = wanted.start if k <= wanted.start else (
            wanted.start + -(-(k - wanted.start) // wanted.step) * wanted.step)
        return j < wanted.stop and self.keyframe_before(j) <= k


#: Packet indexes of the videos opened in this process, by (path, size, mtime): the
#: batch engine's worker processes open the same file once per chunk.
_INDEX_CACHE: dict = {}
_INDEX_CACHE_SIZE = 16


def _video_index(container, stream, path: Path, n: int | None, lossless: bool):
    """The :class:`_PacketIndex` of ``stream`` (None when its packets lack distinct time
    stamps). For a lossless codec (no reordered frames: decode time stamps are the
    presentation ones) from the container's own index when it lists every frame
    (AVI idx1, MP4/MOV sample tables: nothing read), else from one pass over the
    packets (no decoding). Cached per file for this process."""
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns, stream.index)
    except OSError:
        key = None
    if key is not None and key in _INDEX_CACHE:
        return _INDEX_CACHE[key]
    index = _index_from_entries(container, stream, n) if n and lossless else None
    if index is None:
        scan = _packet_scan(container, stream, path)
        stamps = list(scan.stamps)
        if not stamps or any(t is None for t in stamps) or len(set(stamps)) != len(stamps):
            index = None
        else:
            order = sorted(stamps)
            keys = set(t for t, key in zip(stamps, scan.keys) if key)
            if stamps == order:
                # a constant-rate stream whose packets left gaps in its grid of stamps (a
                # damaged stretch): the missing frames keep their places, the later ones theirs
                order = _grid_of_stamps(order, stream.time_base, stream.average_rate) or order
            frame_of = {t: k for k, t in enumerate(order)}
            keys = sorted({0} | {frame_of[t] for t in keys})
            index = _PacketIndex(tuple(order), tuple(keys), stamps == sorted(stamps))
    if key is not None:
        while len(_INDEX_CACHE) >= _INDEX_CACHE_SIZE:
            _INDEX_CACHE.pop(next(iter(_INDEX_CACHE)))
        _INDEX_CACHE[key] = index
    return index


@dataclass(frozen=True)
class _Scan:
    """One pass over a stream's packets without decoding: each packet's stamp and
    keyframe flag in file order, the latest stamp (None where none is known) and the
    duration of its packet (0 where the muxer stored none), in the stream's time base."""

    stamps: tuple
    keys: tuple
    last: int | None
    last_duration: int


def _packet_scan(container, stream, path: Path, at_start: bool = False) -> _Scan:
    """The :class:`_Scan` of ``stream`` (cached per file for this process). A
    stretch the demuxer cannot read ends the scan: the packets before it are
    what the file holds. ``at_start``: the container was just opened (after a
    seek, FFmpeg's MKV demuxer fills in packet durations of its own guessing)."""
    try:
        st = path.stat()
        key = ("scan", str(path.resolve()), st.st_size, st.st_mtime_ns, stream.index)
    except OSError:
        key = None
    if key is not None and key in _INDEX_CACHE:
        return _INDEX_CACHE[key]
    import av

    stamps, keys, last, last_duration = [], [], None, 0
    if not at_start:
        container.seek(0)
    try:
        for p in container.demux(stream):
            if not p.size:
                continue
            stamps.append(p.pts)
            keys.append(bool(p.is_keyframe))
            if p.pts is not None and (last is None or p.pts >= last):
                last, last_duration = p.pts, int(p.duration or 0)
    except av.error.FFmpegError:  # an unreadable stretch: the packets before it
        pass
    container.seek(0)
    scan = _Scan(tuple(stamps), tuple(keys), last, last_duration)
    if key is not None:
        _INDEX_CACHE[key] = scan
    return scan


def _grid_of_stamps(order: list, time_base, rate) -> list | None:
    """The stamps of a constant-rate stream whose packets have ``order`` (increasing)
    but with gaps: every stamp on the grid from the first to the last, the missing
    ones included; None where the stamps are not on one grid of the stream's frame
    period (variable frame rate, or no gap)."""
    if len(order) < 2 or not time_base or not rate:
        return None
    step = min(b - a for a, b in zip(order, order[1:]))
    if step <= 0 or any((b - a) % step for a, b in zip(order, order[1:])):
        return None
    if abs(float(step * time_base) * float(rate) - 1.0) > 0.01:  # not one frame period
        return None
    grid = list(range(order[0], order[-1] + step, step))
    return grid if len(grid) > len(order) else None


def _index_from_entries(container, stream, n: int):
    """The index from the demuxer's own table, when it has one entry per frame with
    increasing stamps and the first packet carries the first stamp; else None."""
    try:
        entries = list(stream.index_entries)
    except AttributeError:  # PyAV before 14 has no index_entries
        return None
    if len(entries) != n or any(e.size <= 0 for e in entries):
        return None
    stamps = [int(e.timestamp) for e in entries]
    if any(b <= a for a, b in zip(stamps, stamps[1:])):
        return None
    container.seek(0)
    first = next((p for p in container.demux(stream) if p.size), None)
    container.seek(0)
    if first is None or first.pts != stamps[0]:
        return None
    keys = sorted({0} | {k for k, e in enumerate(entries) if e.is_keyframe})
    pos_of = None
    if first.pos is not None and first.pos >= 0 and entries[0].pos >= 0:
        offset = first.pos - entries[0].pos  # AVI: the 8-byte chunk header before the data
        pos_of = {e.pos + offset: k for k, e in enumerate(entries)}
        if len(pos_of) != n:
            pos_of = None
    return _PacketIndex(tuple(stamps), tuple(keys), True, pos_of)


def _video_readable_frames(container, stream, path: Path, n: int) -> int | None:
    """How many of the ``n`` frames a video's header promises lie whole in the file (its
    ``readable_frames``), None when all do."""
    whole = _video_whole_frames(container, stream, path, n)
    return whole if whole < n else None


def _video_whole_frames(container, stream, path: Path, n: int) -> int:
    """How many of the ``n`` frames a video's header promises lie whole in the file, in
    order: from the container's own index when it lists ``n`` frames (MP4/MOV sample
    tables, AVI idx1: the frames before the first that ends past the file's end; nothing
    read), else (an AVI cut before its idx1) from one pass over the packets without
    decoding (the frames before the first packet the demuxer found cut short, or ``n``)."""
    try:
        entries = list(stream.index_entries)
    except AttributeError:  # PyAV before 14 has no index_entries
        entries = []
    if len(entries) == n and n > 0:
        try:
            size = path.stat().st_size
        except OSError:
            return n
        ends = [e.pos + e.size if e.pos >= 0 and e.size > 0 else None for e in entries]
        if None not in ends:
            return next((k for k, end in enumerate(ends) if end > size), n)
        return n
    whole = 0
    try:
        container.seek(0)
        for packet in container.demux(stream):
            if not packet.size:
                continue
            if packet.is_corrupt:  # the file ends inside it
                break
            whole += 1
    except Exception:  # an unreadable stretch: the frames before it are what the file holds
        pass
    finally:
        container.seek(0)
    return min(whole, n)


def _frames_of_duration(container, stream, fps: float, counted: int, scan: _Scan | None = None) -> int:
    """The frame count a stream's duration promises where its header stores no count
    (MKV, some MP4), or ``counted`` where the packets reach the end of that duration
    or it is unknown.

    Where the packets' stamps are known (``scan``), the file is whole when its latest
    stamp, plus its packet's duration (or one frame period where that is shorter or
    not stored) and half a tick of rounding, reaches the container's duration (which
    the muxer wrote from those same stamps): a variable frame rate does not make it
    look cut, and a cut of fewer frames than one tick (4 frames of a 5000 frames/s
    MKV with 1 ms stamps) is still seen. A cut file promises the duration x rate
    (+ 1 where packets have no duration: the duration then ends at the last frame's
    start), at least one frame more than it holds. Without stamps: the duration x
    rate, beyond half a frame of rounding."""
    if not fps > 0:
        return counted
    if stream.duration:
        duration_s = float(stream.duration * stream.time_base)
    elif container.duration:
        duration_s = container.duration / 1e6  # AV_TIME_BASE: microseconds
    else:
        return counted
    expected = duration_s * fps
    if scan is not None and scan.last is not None and stream.time_base:
        tick_s = float(stream.time_base)
        last_s = float(scan.last * stream.time_base)
        if last_s + max(1.0 / fps, scan.last_duration * tick_s) + 0.5 * tick_s + 1e-6 >= duration_s:
            return counted
        return max(counted + 1, int(round(expected)) + (0 if scan.last_duration else 1))
    if counted + 0.5 >= expected:
        return counted
    return int(round(expected))


def _first_step_back(stamps) -> int | None:
    """The first packet (in file order) whose stamp is below the one before it."""
    known = [(k, t) for k, t in enumerate(stamps) if t is not None]
    return next((k for (_, a), (k, b) in zip(known, known[1:]) if b < a), None)


def _open_video(path: Path) -> Source:
    try:
        import av
    except ImportError as exc:
        raise _missing("PyAV", "av", "video files") from exc
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as exc:
        raise FormatError(
            f"{str(path)!r} is not a readable video ({exc}); check the file is complete, "
            f"or convert it losslessly, e.g. ffmpeg -i IN -c:v ffvhuff OUT.avi (fast to read)"
        ) from exc
    if not container.streams.video:
        container.close()
        raise FormatError(f"{str(path)!r} has no video stream; give a video file")
    stream = container.streams.video[0]
    ctx = stream.codec_context
    codec = ctx.name
    # FFV1: slice threads only (its frames come in slices, decoded on every core);
    # frame threads cost it ~20 % more CPU a frame (measured 128.5 against 108.6
    # ms per noisy 1024^2 frame) and restart at every chunk's seek. Others: both.
    stream.thread_type = "SLICE" if codec == "ffv1" else "AUTO"
    pix_fmt = ctx.pix_fmt or ""
    rows, cols = int(ctx.height), int(ctx.width)
    rate = stream.average_rate or stream.guessed_rate
    fps = float(rate) if rate else math.nan
    n = int(stream.frames or 0)
    readable = None
    notes = []
    scan = back = None
    try:
        if n <= 0:  # MKV and some MP4 do not store a frame count: count the packets
            scan = _packet_scan(container, stream, path, at_start=True)
            counted = _video_index(container, stream, path, None, False)
            n = len(counted.pts) if counted is not None else len(scan.stamps)
            container.seek(0)
            # (stamps that go back say nothing of where the duration ends)
            back = _first_step_back(scan.stamps)
            promised = n if back is not None else _frames_of_duration(container, stream, fps, n, scan)
            if promised > n:  # the container's duration promises more: the file is cut short
                n, readable = promised, n
        else:  # a header count (AVI, MP4/MOV): the frames it promises may lie past the file's end
            readable = _video_readable_frames(container, stream, path, n)
    except (av.error.FFmpegError, OSError) as exc:  # e.g. EPERM from a seek in a file cut in frame 0
        container.close()
        raise FormatError(
            f"{str(path)!r} is truncated: it ends before its first frame is whole ({exc}); "
            f"copy the file again from its source") from exc
    if n <= 0:
        container.close()
        raise FormatError(f"{str(path)!r} holds no whole video frame (a truncated file?); "
                          f"copy the file again from its source")
    lossless = codec in LOSSLESS_CODECS
    if readable is not None:
        notes.append(
            f"{path.name} is truncated: its container says {n / fps:.6g} s at {fps:g} frames/s "
            f"({n} frames) but holds {readable}; {_span(readable, n)} reported "
            f"UNREADABLE: copy the file again from its source")
    if not lossless:
        notes.append(
            f"{path.name} is compressed with the lossy codec {codec!r}: block artefacts and "
            f"smoothed edges bias Fourier demodulation (heights come out too small and "
            f"noisy); record losslessly (FFV1, raw, PNG) for measurements"
        )
    if back is not None and lossless:  # (reordered frames of other codecs go back by design)
        notes.append(
            f"{path.name}: its time stamps go backwards at frame {back} (a damaged or spliced "
            f"file); frames are numbered in file order and time_s is each frame's own stamp")
    direct = pix_fmt.startswith("gray")  # grey samples as stored, unscaled
    depth = _bits_of_pix_fmt(pix_fmt)
    bits = depth if direct else (16 if depth > 8 else 8)
    if not direct:
        notes.append(f"{path.name} stores {pix_fmt or 'colour'} frames ({depth} bits a sample); "
                     f"they are converted to {bits}-bit grey by FFmpeg (luma, full range)")
    dtype = np.dtype(np.uint16 if bits > 8 else np.uint8)
    time_base = stream.time_base
    # a constant-rate stream whose stamps are coarser than half its frame period (MKV's
    # 1 ms at 5000 frames/s): time_s is the frame's index / rate, not its rounded stamp
    # (AVI's tick is the frame period itself: exact)
    ticks_a_frame = float(time_base) * fps if time_base and fps > 0 else 0.0
    coarse = ticks_a_frame > 0.5 and abs(ticks_a_frame - 1.0) > 1e-3
    if coarse:
        notes.append(
            f"{path.name}: its time stamps ({float(time_base) * 1e3:g} ms) are coarser than "
            f"its frames ({1e3 / fps:.4g} ms apart at {fps:g} frames/s); time_s is the frame's "
            f"index / {fps:g} frames/s from the first frame's stamp")
    start_s = float(stream.start_time * time_base) if coarse and stream.start_time is not None else 0.0

    def convert(frame) -> np.ndarray:
        if not direct:
            return frame.to_ndarray(format="gray16le" if bits > 8 else "gray")
        if frame.format.name in ("gray", "gray8", "gray16le", "gray16be"):
            return frame.to_ndarray()
        return _video_plane0(frame, bits)

    stoppers: list = []

    def close():
        for halt in list(stoppers):
            halt()
        container.close()

    index_box: list = []  # the stream's packet index, built on first need

    def packet_index():
        if not index_box:
            index_box.append(_video_index(container, stream, path, n, lossless))
        return index_box[0]

    def decode_from(first: int, by_pts: bool = True):
        """(decoder, True when frames are identified by their time stamp): seek to the
        keyframe at or before frame ``first`` (found by time stamp) where the packet
        index knows the stamps (also for frame 0, so that a frame the decoder drops
        does not shift the later ones); False means that frames are counted from the
        start of the stream."""
        index = packet_index() if by_pts else None
        if index is not None:
            if first > 0:
                target = index.pts[min(first, len(index.pts) - 1)]
                container.seek(int(target), stream=stream, backward=True, any_frame=False)
            else:
                container.seek(0)
            ctx.flush_buffers()
            return container.decode(stream), True
        container.seek(0)
        ctx.flush_buffers()
        return container.decode(stream), False

    def time_of(frame, i: int) -> float:
        if coarse:
            return start_s + i / fps
        # frames drained from the decoder's threads at the end carry no time base
        if frame.pts is not None and (frame.time_base or time_base):
            return float(frame.pts * (frame.time_base or time_base))
        return i / fps if fps == fps else math.nan

    def decode_error(exc, i: int) -> FormatError:
        return FormatError(
            f"frame {i + 1} of {str(path)!r} cannot be decoded ({exc}); the file may be "
            f"truncated: process the frames before it with --frames :{i + 1}"
        )

    def damaged(k: int, exc) -> FormatError:
        return FormatError(
            f"frame {k} of {str(path)!r} cannot be decoded: its data are damaged ({exc}); "
            f"the frames after it are read from the next keyframe on: copy the file again "
            f"from its source if you need this frame")

    def corrupt(k: int) -> FormatError:
        return FormatError(
            f"frame {k} of {str(path)!r} was decoded with errors: its data are damaged (FFmpeg "
            f"marks the frame corrupt); it is not measured: copy the file again from its source "
            f"if you need it")

    def orphan(k: int, lost: int) -> FormatError:
        return FormatError(
            f"frame {k} of {str(path)!r} cannot be decoded: it is coded as a change from the "
            f"frames before it, and frame {lost} is damaged or missing; the next keyframe and "
            f"the frames after it are read: copy the file again from its source if you need it")

    def frames_by_packet(indices: range, index) -> Iterator[tuple]:
        """Lossless streams (frames in decode order): demux, and send the decoder only
        the packets a wanted frame needs (from the keyframe at or before it), so that
        ``--frames 0::4`` of an intra-only stream decodes a quarter of the frames. One
        seek (to the keyframe before the first frame), then packets in file order.

        Each packet is identified by its place in the container's index (AVI) or its
        stamp, and its frame by its stamp: a packet the damaged file lost is a frame
        missing at its own index (:func:`_accounted` reports it), a packet the decoder
        fails on costs its frame (yielded as an error), and a frame coded as a change
        from a lost or failed one is an error too, up to the next keyframe."""
        frame_of, pos_of = index.frame_of, index.pos_of
        keyframes = frozenset(index.keyframes)
        first_packet = True
        start_key = index.keyframe_before(indices.start)
        container.seek(int(index.pts[start_key]), stream=stream, backward=True, any_frame=False)
        ctx.flush_buffers()
        sent = None  # the frame of the last packet the decoder took without an error
        lost = None  # a frame the ones after it, up to the next keyframe, lack

        def emit(frame):
            k = frame_of.get(frame.pts)
            if k is None:
                raise _Unindexed
            if k in indices:
                if getattr(frame, "is_corrupt", False):  # PyAV 18 on
                    return k, corrupt(k), math.nan
                return k, convert(frame), time_of(frame, k)
            return None

        def identify(packet) -> int | None:
            if pos_of is not None and packet.pos is not None and packet.pos >= 0:
                k = pos_of.get(packet.pos)
                if k is None and first_packet:
                    raise _Unindexed  # positions unlike the index's: decode in order
                return k  # None: a stretch the index does not list (resynchronised)
            k = frame_of.get(packet.pts)
            if k is None:
                raise _Unindexed
            return k

        packets = container.demux(stream)
        while True:
            try:
                packet = next(packets, None)
            except av.error.FFmpegError as exc:  # the demuxer cannot go on
                raise decode_error(exc, sent if sent is not None else indices.start - 1) from exc
            if packet is None:
                break
            if not packet.size:  # the demuxer's end marker: drained below
                continue
            k = identify(packet)
            if k is None:
                continue
            if first_packet:
                first_packet = False
                if k > start_key:  # the seek overshot the keyframe: go on from the start
                    container.seek(0)
                    ctx.flush_buffers()
                    packets = container.demux(stream)
                    continue
            if k >= indices.stop:
                break
            if not index.needed(k, indices):
                continue
            if k not in keyframes and sent != k - 1:  # what it is coded against is lost
                if lost is None:
                    lost = sent + 1 if sent is not None else k
                if k in indices:
                    yield k, orphan(k, lost), math.nan
                continue
            lost = None
            if packet.pts != index.pts[k]:  # the demuxer's count, shifted by a lost packet
                packet.pts = packet.dts = index.pts[k]
            try:
                decoded = ctx.decode(packet)
            except av.error.FFmpegError as exc:
                ctx.flush_buffers()
                sent, lost = None, k
                if k in indices:
                    yield k, damaged(k, exc), math.nan
                continue
            sent = k
            for frame in decoded:
                item = emit(frame)
                if item is not None:
                    yield item
        try:
            drained = ctx.decode(None)  # frames still in the decoder's threads
        except av.error.FFmpegError as exc:
            raise decode_error(exc, sent if sent is not None else indices.start - 1) from exc
        for frame in drained:
            item = emit(frame)
            if item is not None:
                yield item

    def frames(indices: range) -> Iterator[tuple]:
        if readable is not None and indices.stop > readable:  # the rest lie past the cut
            indices = range(indices.start, max(indices.start, readable), indices.step)
        if not len(indices):
            return
        index = packet_index()
        if lossless and index is not None and index.in_decode_order:
            done = -1
            try:
                for item in frames_by_packet(indices, index):
                    done = item[0]
                    yield item
                return
            except _Unindexed:  # a packet or frame without a known stamp: decode in order
                log.debug("%s: a time stamp is not in the packet index; decoding in order", path)
                indices = range(done + indices.step if done >= 0 else indices.start,
                                indices.stop, indices.step)
                if not len(indices):
                    return
        decoded, by_pts = decode_from(indices.start, by_pts=index is not None and not lossless)
        i = -1
        try:
            while True:
                frame = next(decoded, None)
                if frame is None:
                    return
                if by_pts:
                    k = packet_index().frame_of.get(frame.pts)
                    if k is None or (i < 0 and indices.start > 0 and k > indices.start):
                        # a stamp not in the index, or the seek overshot: count from the start
                        decoded.close()
                        decoded, by_pts = decode_from(0, by_pts=False)
                        i = -1
                        continue
                    i = k
                else:
                    i += 1
                if i >= indices.stop:
                    return
                if i in indices:
                    if getattr(frame, "is_corrupt", False):
                        yield i, corrupt(i), math.nan
                    else:
                        yield i, convert(frame), time_of(frame, i)
        except av.error.FFmpegError as exc:
            raise decode_error(exc, i) from exc

    return Source(path, "video", n, (rows, cols), dtype, bits, frame_rate_hz=fps,
                  time_origin="stream start", codec=codec, lossless=lossless, notes=tuple(notes),
                  readable_frames=readable,
                  _frames=lambda indices: _prefetch(frames(indices), stoppers),
                  _close=close, _keyframes=lambda: getattr(packet_index(), "keyframes", None))


def _prefetch(frames: Iterator[tuple], stoppers: list, depth: int = 4) -> Iterator[tuple]:
    """Decode ahead in a thread (FFmpeg releases the GIL), so that decoding a video
    overlaps with processing the frames already decoded; errors are re-raised here,
    in order. Leaving the loop early stops the thread."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run():
        try:
            for item in frames:
                if not put(("frame", item)):
                    return
            put(("end", done))
        except BaseException as exc:  # handed to the consumer, raised there
            put(("error", exc))

    thread = threading.Thread(target=run, name="tirdeflect-video-decode", daemon=True)

    def halt():
        stop.set()
        thread.join(timeout=10)

    stoppers.append(halt)  # the Source stops it before closing the file under it
    thread.start()
    try:
        while True:
            kind, value = q.get()
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        halt()
        stoppers.remove(halt)


# =========================================================================== Photron MRAW (pyMRAW)


def _mraw_files(path: Path) -> tuple:
    """(header path, .mraw path) from either of them."""
    if path.suffix.lower() == ".mraw":
        for suffix in (".cihx", ".cih", ".CIHX", ".CIH"):
            header = path.with_suffix(suffix)
            if header.exists():
                return header, path
        raise FormatError(
            f"{str(path)!r} has no header beside it ({path.with_suffix('.cihx').name} or "
            f"{path.with_suffix('.cih').name}); copy the .cih/.cihx saved with it into the same folder"
        )
    data = path.with_suffix(".mraw")
    if not data.exists():
        alt = path.with_suffix(".MRAW")
        if alt.exists():
            return path, alt
        raise FormatError(
            f"the Photron header {str(path)!r} has no {data.name} beside it; copy the .mraw "
            f"file saved with it into the same folder"
        )
    return path, data


def _cihx_start_frame(header: Path):
    """``frameInfo/startFrame`` of a .cihx (pyMRAW's header dict leaves it out)."""
    import xmltodict

    text = header.read_text(encoding="utf-8", errors="ignore")
    a, b = text.find("<cih>"), text.rfind("</cih>")
    if a < 0 or b < 0:
        return None
    info = xmltodict.parse(text[a:b + len("</cih>")])["cih"].get("frameInfo", {})
    try:
        return int(info.get("startFrame"))
    except (TypeError, ValueError):
        return None


def _open_mraw(path: Path) -> Source:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numba / nose import noise
            import pyMRAW
    except ImportError as exc:
        raise _missing("pyMRAW", "pyMRAW", "Photron MRAW files") from exc
    header, data = _mraw_files(path)
    try:
        cih = pyMRAW.get_cih(str(header))
    except Exception as exc:  # pyMRAW raises bare Exceptions, KeyError, ValueError
        raise FormatError(
            f"the Photron header {str(header)!r} cannot be read ({type(exc).__name__}: {exc}); "
            f"check it is the .cih/.cihx saved by PFV with the recording"
        ) from exc
    try:
        n = int(cih["Total Frame"])
        rows, cols = int(cih["Image Height"]), int(cih["Image Width"])
        color_bit = int(cih["Color Bit"])
        fmt = str(cih.get("File Format", "MRaw"))
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(f"the Photron header {str(header)!r} lacks {exc}; re-save it from PFV") from exc
    if fmt.lower() != "mraw":
        raise FormatError(f"{str(header)!r} describes {fmt} files, not MRAW; open those images instead")
    if color_bit not in (8, 12, 16):
        raise FormatError(
            f"{str(header)!r} says {color_bit} bits per pixel (colour or an unknown packing); "
            f"tirdeflect reads 8, 12 and 16-bit monochrome MRAW: save monochrome in PFV")
    if str(cih.get("Color Type", "Mono")).lower() not in ("mono", "monochrome", ""):
        raise FormatError(f"{str(header)!r} is a colour recording; save it as monochrome MRAW in PFV")
    effective = int(cih.get("EffectiveBit Depth", color_bit) or color_bit)
    side = str(cih.get("EffectiveBit Side", "Lower")).lower()
    bits = min(effective, color_bit) if color_bit == 16 else color_bit
    shift = color_bit - bits if (side == "higher" and color_bit == 16) else 0
    fps = float(cih.get("Record Rate(fps)", math.nan) or math.nan)
    start = cih.get("Start Frame")
    if start is None and header.suffix.lower() == ".cihx":
        start = _cihx_start_frame(header)
    start = int(start) if start is not None else None
    frame_bytes = rows * cols * color_bit // 8
    pixels = rows * cols
    described = -(-n * pixels * color_bit // 8)  # bytes of n frames (12 bit: 2 samples in 3 bytes)
    size = data.stat().st_size
    fits = [b for b in (8, 12, 16) if b != color_bit and n * pixels * b == 8 * size]
    if size != described and fits:
        raise FormatError(
            f"{str(data)!r} is {size} bytes, but its header {header.name} describes {described} "
            f"({n} frames of {rows} x {cols} x {color_bit} bit); the size fits {n} frames of "
            f"{fits[0]} bit: the header's 'Color Bit' ({color_bit}) does not belong to this file"
            + (f" (or its 'Total Frame : {n}' is not this file's)" if size > described else "")
            + ": use the .cih saved with this recording")
    if size < described:
        complete = size * 8 // (pixels * color_bit)
        raise FormatError(
            f"{str(data)!r} holds {size} bytes, fewer than the {n} frames of {rows} x {cols} x "
            f"{color_bit} bit its header announces ({complete} complete); the copy is truncated: "
            f"copy it again, or set 'Total Frame : {complete}' in {header.name}")
    notes = []
    beyond = size * 8 // (pixels * color_bit) - n
    if beyond > 0:
        notes.append(
            f"{data.name} is {size} bytes, {size - described} more than the {n} frames its header "
            f"{header.name} counts ('Total Frame : {n}')"
            f"; it holds {beyond} whole frames beyond them, which are not read: if they belong to "
            f"the recording, set 'Total Frame : {n + beyond}' in {header.name}")
    if not fps > 0:  # (by-hand trial of 7 Dec 2026: time_s NaN with no word)
        notes.append(f"{header.name} gives no frame rate ('Record Rate(fps)' is "
                     f"{cih.get('Record Rate(fps)', 'missing')!r}): the frames have no times (/time_s NaN); "
                     f"set the rate in the header to have them")
    raw = np.memmap(data, dtype=np.uint8, mode="r", shape=(described,))
    dtype = np.dtype(np.uint8 if color_bit == 8 else np.uint16)

    def frame(i: int) -> np.ndarray:
        chunk = raw[i * frame_bytes:(i + 1) * frame_bytes]
        if color_bit == 8:
            return np.array(chunk).reshape(rows, cols)
        if color_bit == 16:
            # Photron writes 16-bit samples little-endian (pyMRAW reads them as native uint16)
            image = np.frombuffer(chunk, dtype="<u2").reshape(rows, cols).astype(np.uint16)
            return image >> shift if shift else image
        if pixels % 2:  # frames start mid-byte every other frame (pyMRAW asserts an even count)
            return _unpack12(raw, i * pixels, pixels).reshape(rows, cols)
        # 12 bit: two samples in three bytes, unpacked by pyMRAW's own decoder
        return pyMRAW.nb_read_uint12(np.ascontiguousarray(chunk)).reshape(rows, cols)

    def frames(indices: range) -> Iterator[tuple]:
        for i in indices:
            time_s = (start + i) / fps if start is not None and fps > 0 else (
                i / fps if fps > 0 else math.nan)
            yield i, frame(i), time_s

    trigger = -start if start is not None and 0 <= -start < n else None
    return Source(path, "mraw", n, (rows, cols), dtype, bits, frame_rate_hz=fps,
                  trigger_index=trigger, time_origin="trigger" if start is not None else "first frame",
                  codec=f"MRAW {color_bit} bit", lossless=True, notes=tuple(notes), _frames=frames,
                  _close=lambda: raw._mmap.close() if getattr(raw, "_mmap", None) else None)


def _unpack12(raw: np.ndarray, first: int, count: int) -> np.ndarray:
    """Samples ``first`` .. ``first + count - 1`` of a packed 12-bit Photron stream
    (two samples in three bytes, big-endian nibbles, as pyMRAW unpacks them), for
    frames of an odd pixel count, which start in the middle of a byte triple."""
    pair0, pair1 = first // 2, (first + count + 1) // 2
    b = np.zeros(3 * (pair1 - pair0), dtype=np.uint16)  # the file's last triple may lack a byte
    part = raw[3 * pair0:3 * pair1]
    b[:len(part)] = part
    b = b.reshape(-1, 3)
    out = np.empty((len(b), 2), dtype=np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] >> 4)
    out[:, 1] = ((b[:, 1] & 15) << 8) | b[:, 2]
    skip = first - 2 * pair0
    return out.ravel()[skip:skip + count]


# =========================================================================== Phantom CINE (PIMS)


def _open_cine(path: Path) -> Source:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from pims.cine import Cine
    except ImportError as exc:
        raise _missing("PIMS", "pims", "Phantom CINE files") from exc
    try:
        cine = Cine(str(path))
    except Exception as exc:  # PIMS raises struct.error, ValueError, KeyError on bad headers
        raise FormatError(
            f"{str(path)!r} is not a readable Phantom CINE file ({type(exc).__name__}: {exc}); "
            f"check the copy is complete, or export it again from PCC"
        ) from exc
    colour = int(cine.cfa) != 0
    n = len(cine)
    try:
        whole = _cine_whole_frames(path, cine, n)
    except Exception:
        cine.close()
        raise
    rows = int(cine.bitmapinfo_dict["bi_height"])
    cols = int(cine.bitmapinfo_dict["bi_width"])
    stored = int(cine.bitmapinfo_dict.get("bi_bit_count", 16))
    bits = int(cine.setup_fields_dict.get("real_bpp", stored) or stored)
    first_no = int(cine.header_dict.get("first_image_no", 0))
    trigger = -first_no if 0 <= -first_no < n else None
    times_s = _cine_times_s(cine, n)
    fps, rate_note = _cine_frame_rate_hz(float(cine.frame_rate or math.nan), times_s)

    def frames(indices: range) -> Iterator[tuple]:
        if colour and len(indices):
            raise FormatError(
                f"{str(path)!r} is a colour recording (Bayer pattern {int(cine.cfa)}, stored "
                f"{'raw' if cine.compression == 2 else 'interpolated'}): a colour filter mosaic "
                f"disturbs the pattern's carriers; record with a monochrome Phantom, or export "
                f"grey frames (TIFF) from PCC")
        for i in indices:
            if i >= whole:
                yield i, _cine_missing(path, i, n, whole), math.nan
                continue
            image = np.asarray(cine._get_frame(i))
            time_s = float(times_s[i]) if times_s is not None else (
                (first_no + i) / fps if fps > 0 else math.nan)
            yield i, np.ascontiguousarray(image), time_s

    dtype = np.dtype(np.uint8 if stored == 8 else np.uint16)
    notes = [f"{path.name} is a colour (CFA) recording; tirdeflect reads monochrome CINE"] if colour else []
    notes += [rate_note] if rate_note else []
    if whole < n:
        notes.append(f"{path.name} is truncated: its header promises {n} frames but the file holds "
                     f"{whole} in full; {_span(whole, n)} reported UNREADABLE: copy it "
                     f"again from the camera or PCC")
    codec = f"CINE {stored} bit" + (f", colour CFA {int(cine.cfa)}" if colour else "")
    return Source(path, "cine", n, (rows, cols), dtype, min(bits, 16), frame_rate_hz=fps,
                  trigger_index=trigger, time_origin="trigger", codec=codec,
                  lossless=True, notes=tuple(notes), _frames=frames, _close=cine.close,
                  readable_frames=whole if whole < n else None)


def _cine_whole_frames(path: Path, cine, n: int) -> int:
    """How many of the ``n`` frames the CINE header promises lie whole in the file:
    the frames before the first whose image (its offset from the image offset table,
    then its annotation block, whose first word is the block's size and last word the
    image's size in bytes) ends past the end of the file."""
    size = path.stat().st_size
    locations = np.asarray(getattr(cine, "image_locations", ()), dtype=np.int64)[:n]
    if len(locations) < n:  # the image offset table itself is cut off: no frame is known
        return 0
    raw = np.memmap(path, dtype=np.uint8, mode="r")
    try:
        def words(at: np.ndarray) -> np.ndarray:  # little-endian uint32 at byte offsets ``at``
            b = raw[at[:, None] + np.arange(4)].astype(np.int64)
            return b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16) | (b[:, 3] << 24)

        ends = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
        fits = (locations >= 0) & (locations + 8 <= size)
        annotation = np.zeros(n, dtype=np.int64)
        annotation[fits] = words(locations[fits])
        fits &= (annotation >= 8) & (locations + annotation <= size)
        image_bytes = np.zeros(n, dtype=np.int64)
        image_bytes[fits] = words(locations[fits] + annotation[fits] - 4)
        ends[fits] = locations[fits] + annotation[fits] + image_bytes[fits]
    finally:
        del raw
    short = np.flatnonzero(ends > size)
    return int(short[0]) if len(short) else n


def _cine_missing(path: Path, i: int, n: int, whole: int) -> FormatError:
    return FormatError(
        f"frame {i} of {str(path)!r} is missing: the file is truncated (its header promises {n} "
        f"frames, it holds {whole} in full; an interrupted copy?): copy it again from the camera "
        f"or PCC, or process the frames before it with --frames :{whole}")


def _cine_times_s(cine, n: int) -> np.ndarray | None:
    """Each frame's time from the trigger in s, from the file's per-frame time stamps;
    None where the file has none.

    The stamps and the trigger are (whole seconds since the epoch, fraction); their
    whole seconds are subtracted apart from the fractions, since one float of
    seconds since 1970 resolves only 0.24 us (PIMS' ``get_time_to_trigger``), a
    percent of a frame interval at 35,000 frames/s.
    """
    try:
        stamps = cine.frame_time_stamps
        trigger = cine.trigger_time
    except Exception:  # no time-stamp block (PIMS raises KeyError/AttributeError/struct.error)
        return None
    if stamps is None or len(stamps) < n:
        return None
    t0, fraction0 = trigger["datetime"], trigger["second_fraction"]
    return np.array([(when - t0).total_seconds() + (fraction - fraction0)
                     for when, fraction in stamps[:n]], dtype=np.float64)


def _cine_frame_rate_hz(header_hz: float, times_s: np.ndarray | None) -> tuple[float, str]:
    """The rate of the frames in the file, in frames/s, and a note where it is not the
    header's.

    A CINE header states the rate the camera recorded at; a file saved from it with a
    step (every k-th frame, in PCC) keeps that rate in its header while its frames lie
    k recording intervals apart. The frames' time stamps say which: where their mean
    interval (over the whole file; single intervals are stamped to the microsecond)
    differs from the header's by over 1 %, the stamps' rate is the file's.
    """
    if times_s is None or len(times_s) < 2 or not times_s[-1] > times_s[0]:
        return header_hz, ""
    stamped_hz = (len(times_s) - 1) / float(times_s[-1] - times_s[0])
    if header_hz > 0 and abs(stamped_hz / header_hz - 1.0) <= 0.01:
        return header_hz, ""
    step = f" (1 in {round(header_hz / stamped_hz)} recorded frames saved)" if header_hz > 1.5 * stamped_hz else ""
    return stamped_hz, (
        f"the header's {header_hz:g} frames/s is the recording rate; the frames in this file "
        f"are {1e6 / stamped_hz:.4g} us apart{step}: rate and times come from the frames' "
        f"time stamps ({stamped_hz:.6g} frames/s)")
