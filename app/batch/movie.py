"""Movies of processed maps for talks (``tirdeflect movie``), encoded with PyAV.

Each movie frame shows one map of OUT.h5 (height in micrometres, or a slope in
milliradians) in a fixed colour range for the whole movie, a colour bar with
its scale, and the frame's stamp (:func:`frame_stamps`): its number, time and,
for a triggered recording, its index from the trigger, and in red what makes it
other than a plain measurement (invalid, recorded incomplete, frames lost before
it). Unmeasured samples are grey.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.batch.frame_status import FrameStatus
from app.batch.probe import NO_TRIGGER_INDEX, frame_times, frames_done, open_output
from app.files.h5safe import check_creatable
from drivers.base import FrameFlags
from processing.errors import TirdeflectError

__all__ = ["MovieReport", "make_movie", "QUANTITIES", "colour_range", "frame_stamps"]

#: quantity -> (dataset, factor from stored units to displayed, displayed unit, label)
QUANTITIES = {
    "height": ("height", 1e3, "um", "height"),
    "slope_x": ("slope_x", 1e3, "mrad", "slope dh/dx"),
    "slope_y": ("slope_y", 1e3, "mrad", "slope dh/dy"),
}

_BAR_W = 110   # colour bar panel, px
_TOP_H = 52    # text band above the map, px: the stamp, and under it the mark
_GREY = (96, 96, 96)
_MARK_RGB = (200, 0, 0)
#: flags of a recorded frame that say frames were lost just before it
_LOST_BEFORE = FrameFlags.ID_GAP_BEFORE | FrameFlags.TIME_GAP_BEFORE | FrameFlags.RING_OVERRUN_BEFORE


@dataclass
class MovieReport:
    path: Path
    frames: int
    width: int
    height: int
    value_range: tuple
    unit: str
    codec: str
    #: the values' extremes over every frame (displayed units), and the frame of each
    extremes: tuple = (float("nan"), float("nan"))
    extreme_frames: tuple = (-1, -1)

    def beyond_range(self) -> str:
        """Where the values reach far beyond the colour range (by half its width or more: a drop's or an
        impact's peaks, under the percentiles of the many quiet samples, shown flat at the range's end), what
        they reach and how to show them; "" where they do not (by-hand trial of 7 Dec 2026: the drop's peaks
        clipped in silence)."""
        lo, hi = self.value_range
        low, high = self.extremes
        margin = 0.5 * (hi - lo)
        far = [(v, k) for v, k, out in ((low, self.extreme_frames[0], low < lo - margin),
                                        (high, self.extreme_frames[1], high > hi + margin)) if out]
        if not far:
            return ""
        where = " and ".join(f"{v:.4g} {self.unit} (frame {k})" for v, k in far)
        return (f"the values reach {where}, beyond the colour range {lo:.4g} .. {hi:.4g} {self.unit} taken from "
                f"the percentiles: there they show as its end colour; --range {low:.4g},{high:.4g} shows them "
                f"whole")


def colour_range(ds, n: int, factor: float, percentile: float, max_samples: int = 60) -> tuple:
    """(low, high) in displayed units: the ``percentile`` and ``100 - percentile``
    percentiles of the finite values of up to ``max_samples`` frames spread over the movie."""
    picks = np.unique(np.linspace(0, n - 1, min(n, max_samples)).round().astype(int))
    values = []
    for k in picks:
        v = np.asarray(ds[k], dtype=np.float64).ravel()
        v = v[np.isfinite(v)]
        if v.size > 20000:
            v = v[:: v.size // 20000]
        values.append(v)
    values = np.concatenate(values) * factor if values else np.empty(0)
    if values.size == 0:
        raise TirdeflectError("no frame of the file holds a measured value; nothing to show")
    lo, hi = np.percentile(values, [percentile, 100.0 - percentile])
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    return float(lo), float(hi)


def frame_stamps(f, n: int, times=None) -> list:
    """What each of the first ``n`` frames of an opened OUT.h5 is stamped with: ``(line, mark)``.

    ``line``: ``frame K   t = T s`` (its index in the input sequence, ``/frame_index``, and its time
    where known, ``times`` or :func:`app.batch.probe.frame_times`), then, for a frame of a triggered
    recording, its index from the trigger frame, ``/trigger_index``: ``trigger -3`` before it,
    ``trigger 0`` on it, ``trigger +12`` after it (a recording stopped before its trigger: counted
    back from the stop). ``mark``: what makes the map other than a plain measurement, "" for none:
    ``INVALID: <why>`` (``/frame_status``: no heights, the map all grey), ``INCOMPLETE`` (recorded
    with pixels missing), ``frames lost before`` (camera id or time gap, ring overrun; with
    ``--step`` also before the frames stepped over), from ``/frame_flags``; joined by "; ".
    """
    if times is None:
        times, _ = frame_times(f, n)
    index = np.asarray(f["frame_index"][:n])
    trigger, status, flags = (np.asarray(f[name][:n], dtype=np.int64) if name in f else np.full(n, missing)
                              for name, missing in (("trigger_index", NO_TRIGGER_INDEX), ("frame_status", 0),
                                                    ("frame_flags", 0)))
    stamps = []
    for k in range(n):
        line = f"frame {int(index[k])}" + (f"   t = {times[k]:.4f} s" if math.isfinite(times[k]) else "")
        if trigger[k] != NO_TRIGGER_INDEX:
            line += f"   trigger {int(trigger[k]):+d}" if trigger[k] else "   trigger 0"
        stamps.append((line, _mark(int(status[k]), int(flags[k]))))
    return stamps


def _mark(status: int, flags: int) -> str:
    """The red words of a frame's stamp (:func:`frame_stamps`); "" for a plain measurement."""
    marks = []
    if status != FrameStatus.OK:
        try:
            why = FrameStatus(status).label
        except ValueError:  # a status this version does not know
            why = f"status {status}"
        marks.append(f"INVALID: {why}")
    if flags & FrameFlags.INCOMPLETE:
        marks.append("INCOMPLETE")
    if flags & _LOST_BEFORE:
        marks.append("frames lost before")
    return "; ".join(marks)


def _put_text(canvas, text: str, x: int, y: int, width: int, scale: float, rgb, thickness: int = 1) -> None:
    """``text`` at ``(x, y)`` (its baseline's start), its font made smaller where it would be wider than
    ``width`` px."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    wide = cv2.getTextSize(text, font, scale, thickness)[0][0]
    if wide > width > 0:
        scale *= width / wide
    cv2.putText(canvas, text, (x, y), font, scale, rgb, thickness, cv2.LINE_AA)


def _colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    import cv2

    scaled = np.clip((values - lo) / (hi - lo), 0.0, 1.0)
    idx = np.nan_to_num(scaled * 255.0, nan=0.0).astype(np.uint8)
    rgb = cv2.applyColorMap(idx, cv2.COLORMAP_VIRIDIS)[:, :, ::-1]
    rgb = np.ascontiguousarray(rgb)
    rgb[~np.isfinite(values)] = _GREY
    return rgb


def _ticks(lo: float, hi: float, count: int = 5) -> list:
    span = hi - lo
    raw = span / max(count - 1, 1)
    mag = 10 ** math.floor(math.log10(raw)) if raw > 0 else 1.0
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=mag * 10)
    first = math.ceil(lo / step) * step
    ticks = []
    v = first
    while v <= hi + 1e-9 * span:
        ticks.append(v)
        v += step
    return ticks


def _compose(map_rgb, lo, hi, unit, label, stamp, scale, aspect):
    """One movie frame (RGB, even width and height): text band (``stamp``: the ``(line, mark)`` of
    :func:`frame_stamps`, the mark in red under the line), map, colour bar.

    The map is magnified ``scale`` times along x and ``scale * aspect`` along y
    (``aspect`` = mm per row / mm per column), so the surface shows at its true shape."""
    import cv2

    rows, cols = map_rgb.shape[:2]
    out_rows = int(round(rows * scale * aspect))
    if scale != 1 or out_rows != rows:
        map_rgb = cv2.resize(map_rgb, (cols * scale, out_rows), interpolation=cv2.INTER_NEAREST)
        rows, cols = out_rows, cols * scale
    height = _TOP_H + rows + 10
    width = cols + _BAR_W
    height += height % 2
    width += width % 2
    canvas = np.full((height, width, 3), 255, np.uint8)
    canvas[_TOP_H:_TOP_H + rows, :cols] = map_rgb
    font = cv2.FONT_HERSHEY_SIMPLEX
    line, mark = stamp
    _put_text(canvas, line, 6, _TOP_H - 31, cols - 12, 0.55, (0, 0, 0))
    if mark:
        _put_text(canvas, mark, 6, _TOP_H - 9, cols - 12, 0.55, _MARK_RGB, 2)
    # colour bar
    x0, x1 = cols + 14, cols + 34
    y0, y1 = _TOP_H + 8, _TOP_H + rows - 8
    ramp = np.linspace(hi, lo, max(y1 - y0, 2))[:, None] * np.ones((1, x1 - x0))
    canvas[y0:y0 + ramp.shape[0], x0:x1] = _colormap(ramp, lo, hi)
    cv2.rectangle(canvas, (x0, y0), (x1 - 1, y0 + ramp.shape[0] - 1), (0, 0, 0), 1)
    for t in _ticks(lo, hi):
        y = int(round(y0 + (hi - t) / (hi - lo) * (ramp.shape[0] - 1)))
        cv2.line(canvas, (x1, y), (x1 + 4, y), (0, 0, 0), 1)
        text = f"{t:.3g}"
        cv2.putText(canvas, text, (x1 + 7, y + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, f"{label}", (cols + 6, _TOP_H - 18), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, f"[{unit}]", (cols + 6, _TOP_H - 5), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def _encoder(container, suffix: str, fps: float):
    from fractions import Fraction

    import av

    rate = Fraction(fps).limit_denominator(1001)
    for codec in (("mpeg4",) if suffix == ".avi" else ("libx264", "h264", "mpeg4")):
        try:
            av.codec.Codec(codec, "w")
        except Exception:
            continue
        stream = container.add_stream(codec, rate=rate)
        stream.pix_fmt = "yuv420p"
        if codec != "mpeg4":
            stream.options = {"crf": "18"}
        else:
            stream.bit_rate = 8_000_000
        return stream
    raise TirdeflectError("this FFmpeg (PyAV) has no H.264 or MPEG-4 encoder; reinstall av")


def make_movie(out_h5, movie_path, *, quantity: str = "height", value_range=None,
               percentile: float = 1.0, fps: float | None = None, overwrite: bool = False,
               scale: int | None = None, on_progress=None) -> MovieReport:
    """Write a movie of ``quantity`` from a ``tirdeflect process`` output.

    Parameters
    ----------
    out_h5 : path-like
        OUT.h5 of ``tirdeflect process``.
    movie_path : path-like
        .mp4, .mkv, .mov (H.264) or .avi (MPEG-4).
    quantity : {"height", "slope_x", "slope_y"}
    value_range : (low, high) or None
        Colour range in displayed units (um for height, mrad for slopes); None:
        the ``percentile`` .. ``100 - percentile`` percentiles over the movie.
    fps : float or None
        Movie frame rate; None: from the frames' time stamps (real time), else 25.
    scale : int or None
        Integer magnification of the map along x; None: enough to make it
        >= 480 px wide. Rows are stretched by (mm per row) / (mm per column) on
        top, so the surface keeps its true shape (TIR rows span 1/cos(theta) more).
    on_progress : callable or None
        ``on_progress(done, total)`` after each frame.
    """
    import av

    movie = _checked_movie_path(movie_path, quantity, overwrite, percentile)
    name, factor, unit, label = QUANTITIES[quantity]
    with open_output(out_h5) as f:
        n = frames_done(f)
        if n == 0:
            raise TirdeflectError(f"{str(out_h5)!r} holds no processed frame (frames_done = 0)")
        ds = f[name]
        lo, hi = _value_range(ds, n, factor, percentile, value_range)
        times, _ = frame_times(f, n)
        fps = _movie_fps(times, fps)
        stamps = frame_stamps(f, n, times)
        scale, aspect = _magnification(f, ds.shape[1:], scale)
        container = av.open(str(movie), "w")
        try:
            stream = None
            extremes, extreme_frames = [np.inf, -np.inf], [-1, -1]
            for k in range(n):
                values = np.asarray(ds[k], dtype=np.float64) * factor
                if np.isfinite(values).any():
                    if np.nanmin(values) < extremes[0]:
                        extremes[0], extreme_frames[0] = float(np.nanmin(values)), k
                    if np.nanmax(values) > extremes[1]:
                        extremes[1], extreme_frames[1] = float(np.nanmax(values)), k
                image = _compose(_colormap(values, lo, hi), lo, hi, unit, label, stamps[k], scale, aspect)
                if stream is None:
                    stream = _encoder(container, movie.suffix.lower(), fps)
                    stream.width, stream.height = image.shape[1], image.shape[0]
                for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                    container.mux(packet)
                if on_progress is not None:
                    on_progress(k + 1, n)
            for packet in stream.encode():
                container.mux(packet)
        except BaseException:
            container.close()
            movie.unlink(missing_ok=True)  # no half movie left behind
            raise
        container.close()
    return MovieReport(movie, n, int(stream.width), int(stream.height), (lo, hi), unit,
                       stream.codec_context.name, tuple(extremes), tuple(extreme_frames))


def _checked_movie_path(movie_path, quantity: str, overwrite: bool, percentile: float) -> Path:
    """The movie's path, once the arguments are checked (before any frame is drawn)."""
    if quantity not in QUANTITIES:
        raise TirdeflectError(f"unknown quantity {quantity!r}; choose {', '.join(QUANTITIES)}")
    movie = Path(movie_path)
    if movie.suffix.lower() not in (".mp4", ".mkv", ".mov", ".avi"):
        raise TirdeflectError(f"--out {str(movie)!r}: give a .mp4, .mkv, .mov or .avi file name")
    if movie.exists() and not overwrite:
        raise TirdeflectError(f"{str(movie)!r} already exists; choose another --out or add --overwrite")
    if not (movie.parent if str(movie.parent) else Path(".")).is_dir():
        raise TirdeflectError(f"the folder of --out {str(movie)!r} does not exist; create it first")
    check_creatable(movie, "choose another --out (a folder you can write to)")
    if not 0 <= percentile < 50:
        raise TirdeflectError(f"--percentile must be in [0, 50); got {percentile}")
    return movie


def _value_range(ds, n: int, factor: float, percentile: float, value_range) -> tuple:
    """The colour range: ``value_range`` checked, else from the percentiles (:func:`colour_range`)."""
    if value_range is None:
        return colour_range(ds, n, factor, percentile)
    lo, hi = (float(v) for v in value_range)
    if not hi > lo:
        raise TirdeflectError(f"--range {lo:g},{hi:g}: the high end must exceed the low end")
    return lo, hi


def _movie_fps(times, fps):
    """``fps`` checked, else real time from the frames' ``times`` (25 without them); within 1..240."""
    if fps is None:
        dt = np.diff(times)
        dt = dt[np.isfinite(dt)]  # between frames that both have a time (not the unreadable ones)
        fps = 1.0 / float(np.median(dt)) if len(dt) and np.median(dt) > 0 else 25.0
    if not (fps > 0 and math.isfinite(fps)):
        raise TirdeflectError(f"--fps must be a positive number; got {fps}")
    return min(max(fps, 1.0), 240.0)  # players cope with 1..240 frames/s


def _magnification(f, shape, scale):
    """``(scale, aspect)``: the map's magnification along x (``scale``, else enough for 480 px) and
    the rows' stretch on top of it, (mm per row) / (mm per column)."""
    rows, cols = shape
    x_mm, y_mm = f["x_mm"][()], f["y_mm"][()]
    aspect = 1.0
    if rows > 1 and cols > 1:
        aspect = abs(float(y_mm[-1] - y_mm[0]) / (rows - 1)) / abs(float(x_mm[-1] - x_mm[0]) / (cols - 1))
    if scale is None:
        scale = max(1, int(math.ceil(480 / cols)))
    return scale, aspect
