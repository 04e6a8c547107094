"""Live image views: a pyqtgraph ImageItem with axes in mm and a colour bar in physical units.

Live video follows /work/shared/style.md: ``ImageItem`` in a plot (not ``ImageView``),
explicit levels, ``autoLevels=False``, C-contiguous float32/uint8 arrays. Levels
follow the data (robust percentiles of a subsample, at most a few times per
second) until the user drags the colour bar; "Auto levels" in the view's context
menu gives control back.
"""

from __future__ import annotations

import collections
import time
from typing import Optional, Sequence, Tuple

import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore, QtWidgets

__all__ = ["ImageView", "ProfileView", "HistogramView", "SpectrumView", "robust_levels"]

# every ImageItem here is created with axisOrder="row-major"; no global pyqtgraph options are changed


def robust_levels(data: np.ndarray, *, symmetric: bool = False, lo_pct: float = 1.0,
                  hi_pct: float = 99.0, max_samples: int = 20000) -> Tuple[float, float]:
    """Display levels from percentiles of a subsample, ignoring NaN.

    Parameters
    ----------
    data : ndarray
        Any 2-D array (NaN allowed).
    symmetric : bool
        Levels ``(-m, m)`` around zero (heights, slopes).
    lo_pct, hi_pct : float
        Percentiles for the low and high level.

    Returns
    -------
    (float, float)
        Low and high level, ``low < high`` always.
    """
    flat = data.ravel()
    step = max(1, flat.size // max_samples)
    sub = flat[::step]
    if sub.dtype.kind == "f":
        sub = sub[np.isfinite(sub)]
    if sub.size == 0:
        return (0.0, 1.0)
    if symmetric:
        m = float(np.percentile(np.abs(sub), hi_pct))
        m = m if m > 0 else 1.0
        return (-m, m)
    lo, hi = (float(v) for v in np.percentile(sub, [lo_pct, hi_pct]))
    if not hi > lo:
        hi = lo + 1.0
    return (lo, hi)


def _cache_axes(plot_item) -> None:
    """Paint a plot's axes and title from pixmap caches (redrawn only when they change); dark text."""
    cache = QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache
    for side in ("left", "bottom", "top", "right"):
        axis = plot_item.getAxis(side)
        if axis is not None:
            axis.setCacheMode(cache)
            axis.setTextPen("#222")
            axis.setPen("#444")
            if axis.labelText:
                axis.setLabel(axis.labelText, units=axis.labelUnits or None, color="#222")
    plot_item.titleLabel.setCacheMode(cache)


class _Graphics(pg.GraphicsLayoutWidget):
    """GraphicsLayoutWidget that records when it really painted (for shown fps and camera-to-screen latency)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.painted = 0
        self.last_paint_ns = 0
        self.pending_stamp_ns = 0  # host timestamp of data set but not yet painted
        self.latencies_ms = collections.deque(maxlen=2000)

    def paintEvent(self, ev):
        super().paintEvent(ev)
        self.painted += 1
        self.last_paint_ns = time.monotonic_ns()
        if self.pending_stamp_ns:
            self.latencies_ms.append((self.last_paint_ns - self.pending_stamp_ns) / 1e6)
            self.pending_stamp_ns = 0


class ImageView(QtWidgets.QWidget):
    """One live map: title, image with axes (mm or px), colour bar with units.

    Parameters
    ----------
    title : str
        Shown above the image.
    units : str
        Colour-bar label, e.g. "height (µm)".
    cmap : str
        pyqtgraph colour map name.
    symmetric : bool
        Auto levels symmetric around zero.
    axis_units : str
        Label of both axes ("mm" or "px").
    """

    def __init__(self, title: str, units: str, *, cmap: str = "viridis", symmetric: bool = False,
                 axis_units: str = "mm", parent=None, levels_interval_s: float = 0.5):
        super().__init__(parent)
        self.title = title
        self.units = units
        self.symmetric = symmetric
        self.auto_levels = True
        self._levels_interval_s = levels_interval_s
        self._levels_t = 0.0
        self._levels: Tuple[float, float] = (0.0, 1.0)
        self._levels_set = False
        self._rect = None
        self._shape = None
        self.updates = 0
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.graphics = _Graphics()
        self.graphics.setBackground("w")
        layout.addWidget(self.graphics)
        self.plot = self.graphics.addPlot()
        self.plot.setTitle(f"<b>{title}</b>", color="#111", size="11pt")
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)  # row 0 at the top, like the camera image
        for side, name in (("bottom", "x"), ("left", "y")):
            axis = self.plot.getAxis(side)
            axis.enableAutoSIPrefix(False)
            axis.setLabel(f"{name} ({axis_units})")
            axis.setTextPen("#222")
            axis.setPen("#444")
        self.image = pg.ImageItem(axisOrder="row-major")
        # decimate by striding in set_data (pyqtgraph's auto downsample averages: ~10 ms at 1024^2)
        self.image.setAutoDownsample(False)
        self.stride = 1
        self.plot.addItem(self.image)
        cmap_obj = cmap if isinstance(cmap, pg.ColorMap) else pg.colormap.get(cmap)
        self.colorbar = pg.ColorBarItem(values=(0, 1), colorMap=cmap_obj, label=None,
                                        interactive=True, width=14)
        self.colorbar.setImageItem(self.image, insert_in=self.plot)
        cb_axis = getattr(self.colorbar, "axis", None)
        if cb_axis is not None:
            cb_axis.setTextPen("#222")
            cb_axis.setLabel(units, color="#222")
            cb_axis.enableAutoSIPrefix(False)  # units are in the label already
        self.colorbar.sigLevelsChangeFinished.connect(self._user_levels)
        self._setting_levels = False
        act = self.plot.getViewBox().menu.addAction("Auto levels")
        act.triggered.connect(self.reset_levels)
        self._cache_static_items()
        self.message = pg.TextItem("", color=(200, 0, 0), anchor=(0, 0))
        self.message.setZValue(100)
        self.plot.addItem(self.message)

    def _cache_static_items(self):
        """Paint axes, colour bar and title from pixmap caches: only the image is redrawn per frame."""
        cache = QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache
        items = [self.plot.getAxis(side) for side in ("left", "bottom", "top", "right")]
        items += [self.plot.titleLabel, self.colorbar]
        items += [c for c in self.colorbar.childItems()]
        for item in items:
            if item is not None:
                item.setCacheMode(cache)

    # ------------------------------------------------------------------
    def _user_levels(self, *_):
        if not self._setting_levels:
            self.auto_levels = False

    def reset_levels(self) -> None:
        """Let the levels follow the data again."""
        self.auto_levels = True
        self._levels_t = 0.0

    def set_levels(self, levels: Tuple[float, float]) -> None:
        """Fix the levels (stops auto levels)."""
        self.auto_levels = False
        self._apply_levels(levels)

    def _apply_levels(self, levels):
        levels = (float(levels[0]), float(levels[1]))
        if levels == self._levels and self._levels_set:
            return  # unchanged: do not invalidate the colour bar's cached axis
        self._levels_set = True
        self._levels = levels
        self._setting_levels = True
        try:
            self.colorbar.setLevels(self._levels)
        finally:
            self._setting_levels = False

    @property
    def levels(self) -> Tuple[float, float]:
        return self._levels

    def set_data(self, data: np.ndarray, *, x: Optional[np.ndarray] = None,
                 y: Optional[np.ndarray] = None, levels: Optional[Tuple[float, float]] = None,
                 stamp_ns: int = 0) -> None:
        """Show ``data`` (2-D), placed at coordinates ``x`` (cols) and ``y`` (rows) if given.

        Parameters
        ----------
        data : ndarray, shape (rows, cols)
            float32 (NaN shown transparent) or uint8/uint16.
        x, y : ndarray, optional
            Column and row coordinates (mm) of the pixel centres; pixels otherwise.
        levels : (float, float), optional
            Explicit levels for this frame (otherwise auto/held levels).
        stamp_ns : int
            ``time.monotonic_ns()`` when the camera delivered the data; the
            view records camera-to-screen latency when it next paints.
        """
        if data.dtype.kind == "f" and data.dtype != np.float32:
            data = data.astype(np.float32)
        full_shape = data.shape
        stride = self._stride_for(full_shape)
        if stride > 1:  # never draw more pixels than the screen shows
            data = data[::stride, ::stride]
        data = np.ascontiguousarray(data)
        now = time.monotonic()
        if levels is not None:
            self._apply_levels(levels)
        elif self.auto_levels and (data.size <= 65536 or now - self._levels_t >= self._levels_interval_s
                                   or self._shape != full_shape):
            # Small (decimated) maps are checked every frame (< 1 ms), large ones a few times per second.
            # The colour bar (whose axis is costly to redraw) moves at once when the data range doubled or
            # shrank to a quarter, otherwise at most every levels_interval_s and only by > 10 %.
            lo, hi = robust_levels(data, symmetric=self.symmetric)
            old_lo, old_hi = self._levels
            span = max(old_hi - old_lo, 1e-30)
            new_span = hi - lo
            jump = new_span > 2 * span or new_span < 0.25 * span or lo < old_lo - span or hi > old_hi + span
            due = now - self._levels_t >= self._levels_interval_s
            moved = abs(lo - old_lo) > 0.1 * span or abs(hi - old_hi) > 0.1 * span
            if self._shape != full_shape or not self._levels_set or jump or (due and moved):
                self._apply_levels((lo, hi))
                self._levels_t = now
        self.image.setImage(data, autoLevels=False, levels=self._levels)
        rect = self._rect_for(full_shape, x, y)
        if rect != self._rect:
            self.image.setRect(QtCore.QRectF(*rect))
            self._rect = rect
            self.plot.getViewBox().autoRange(padding=0.0)
        self._shape = full_shape
        self.updates += 1
        if stamp_ns:
            self.graphics.pending_stamp_ns = stamp_ns

    def _stride_for(self, shape) -> int:
        """Integer decimation so that the drawn image has about as many pixels as the view on screen."""
        vb = self.plot.getViewBox()
        w = max(int(vb.width()), 64)
        h = max(int(vb.height()), 64)
        stride = int(min(shape[0] / h, shape[1] / w))
        self.stride = max(1, stride)
        return self.stride

    @staticmethod
    def _rect_for(shape, x, y):
        rows, cols = shape
        if x is None or y is None or len(x) < 2 or len(y) < 2:
            return (0.0, 0.0, float(cols), float(rows))
        dx = (float(x[-1]) - float(x[0])) / (len(x) - 1)
        dy = (float(y[-1]) - float(y[0])) / (len(y) - 1)
        return (float(x[0]) - dx / 2, float(y[0]) - dy / 2, dx * cols, dy * rows)

    def show_message(self, text: str) -> None:
        """Overlay a (red) message, e.g. why there is no map; empty string hides it."""
        self.message.setText(text)
        if self._rect is not None:
            self.message.setPos(self._rect[0], self._rect[1])

    def current_data(self) -> Optional[np.ndarray]:
        return self.image.image


class ProfileView(QtWidgets.QWidget):
    """Height profile along a line: a plot of value vs distance along the line (mm)."""

    def __init__(self, title: str = "Profile", units: str = "height (µm)", parent=None):
        super().__init__(parent)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.plot = pg.PlotWidget()
        self.plot.setTitle(f"<b>{title}</b>", color="#111", size="11pt")
        self.plot.setBackground("w")
        self.plot.setLabel("bottom", "distance along the line (mm)")
        self.plot.setLabel("left", units)
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        self.curve = self.plot.plot(pen=pg.mkPen("#1f77b4", width=2))
        self.plot.enableAutoRange(False)  # ranges set explicitly: axes are not redrawn every frame
        _cache_axes(self.plot.getPlotItem())
        self._range = None
        self._range_t = 0.0
        layout.addWidget(self.plot)

    def set_profile(self, distance_mm: np.ndarray, values: np.ndarray,
                    y_range: Optional[Tuple[float, float]] = None) -> None:
        """Plot ``values`` against ``distance_mm``; ``y_range`` (e.g. the map's colour levels) fixes the y axis."""
        d = np.asarray(distance_mm, float)
        v = np.asarray(values, float)
        self.curve.setData(d, v, connect="finite")
        finite = v[np.isfinite(v)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        if y_range is not None:  # at least the map's colour levels, and everything on the line
            lo, hi = min(lo, float(y_range[0])), max(hi, float(y_range[1]))
        if not hi > lo:
            hi = lo + 1.0
        now = time.monotonic()
        x1 = float(d[-1]) if d.size else 1.0
        old = self._range
        # expand at once when the curve leaves the plot; shrink or move at most once a second
        grow = old is None or lo < old[2] or hi > old[3] or x1 != old[1]
        if grow or (now - self._range_t > 1.0 and (lo, hi) != old[2:]):
            rng = (0.0, x1, lo, hi)
            self.plot.setRange(xRange=rng[:2], yRange=rng[2:], padding=0.05)
            self._range = rng
            self._range_t = now


class HistogramView(QtWidgets.QWidget):
    """Histogram of raw pixel values (log counts) with the saturation percentage."""

    def __init__(self, parent=None):
        super().__init__(parent)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.plot = pg.PlotWidget()
        self.plot.setBackground("w")
        self.plot.setLabel("bottom", "pixel value")
        self.plot.setLabel("left", "pixels (log10)")
        self.plot.setMaximumHeight(170)
        self.curve = self.plot.plot(stepMode="center", fillLevel=0, brush=(80, 80, 200, 120),
                                    pen=pg.mkPen("#3040a0"))
        self.plot.enableAutoRange(False)
        _cache_axes(self.plot.getPlotItem())
        layout.addWidget(self.plot)
        self._title = ""
        self._range = None

    def set_image(self, image: np.ndarray, bit_depth: int, saturation_pct: float) -> None:
        top = (1 << int(bit_depth)) - 1
        sub = image[::4, ::4].ravel()
        nbins = 256
        if image.dtype == np.uint8 and bit_depth == 8:
            counts = np.bincount(sub, minlength=256)[:256]
        else:
            counts, _ = np.histogram(sub, bins=nbins, range=(0, top + 1))
        edges = np.linspace(0, top + 1, nbins + 1)
        logc = np.log10(counts.astype(float) + 1.0)
        self.curve.setData(edges, logc)
        ymax = float(np.ceil(logc.max() + 0.25)) if logc.size else 1.0
        if self._range != (top, ymax):
            self.plot.setRange(xRange=(0, top + 1), yRange=(0, ymax), padding=0.02)
            self._range = (top, ymax)
        title = f"<b>Histogram</b> · {saturation_pct:.2f} % saturated"
        if title != self._title:
            self.plot.setTitle(title, color="#b00000" if saturation_pct > 0.5 else "#222")
            self._title = title


class SpectrumView(ImageView):
    """Log-magnitude spectrum with the detected carrier peaks marked."""

    def __init__(self, parent=None):
        super().__init__("Spectrum (log |FFT|)", "log10 |F|", cmap="inferno", axis_units="cycles/px",
                         parent=parent)
        self.carriers = pg.ScatterPlotItem(size=18, pen=pg.mkPen("c", width=2), brush=None, symbol="o")
        self.carriers.setZValue(10)
        self.plot.addItem(self.carriers)

    def set_spectrum(self, magnitude: np.ndarray, freq_x: Optional[np.ndarray],
                     freq_y: Optional[np.ndarray], carriers: Sequence[Tuple[float, float]]) -> None:
        """Show ``magnitude`` at frequencies ``freq_x`` (cols) ``freq_y`` (rows), circles at ``carriers`` (fx, fy)."""
        mag = np.asarray(magnitude, np.float32)
        self.set_data(mag, x=freq_x, y=freq_y,
                      levels=robust_levels(mag, lo_pct=50.0, hi_pct=99.95) if self.auto_levels else None)
        pts = [{"pos": (float(fx), float(fy))} for fx, fy in carriers]
        self.carriers.setData(pts)
