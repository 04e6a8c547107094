"""Live image views: a pyqtgraph ImageItem with axes in mm and a colour bar in physical units.

Live video follows the style guide (pyqtgraph's examples for live plots): ``ImageItem`` in a plot (not ``ImageView``),
explicit levels, ``autoLevels=False``, C-contiguous float32/uint8 arrays. Levels
follow the data (robust percentiles of a subsample, at most a few times per
second) until the user drags the colour bar; "Auto levels" in the view's context
menu gives control back.
"""

from __future__ import annotations

import collections
import math
import time
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

from .model.colour_range import CAMERA, ColourRule, data_levels, range_moves, robust_levels, without_spread

__all__ = ["ImageView", "ProfileView", "HistogramView", "SpectrumView", "ProfileLine", "decimate_for_display",
           "room_for_the_last_tick"]

# every ImageItem here is created with axisOrder="row-major"; no global pyqtgraph options are changed


class _Overlay(QtWidgets.QLabel):
    """A wrapped message drawn over a plot; the full text is also its tooltip."""

    def __init__(self, parent, style: str, below: "_Overlay" = None):
        super().__init__(parent)
        self.below = below  # placed under this one when it shows
        self.setWordWrap(True)
        self.setStyleSheet(style)
        self.setTextFormat(QtCore.Qt.PlainText)
        self.setAttribute(QtCore.Qt.WA_TransparentForMouseEvents)
        self.hide()

    def toPlainText(self) -> str:
        return self.text()

    def set_message(self, text: str) -> None:
        if text == self.text():
            return
        self.setText(text)
        self.setToolTip(text)
        self.setVisible(bool(text))
        self.place()

    def place(self) -> None:
        """Across the top (or bottom) of the parent, as tall as the wrapped text needs."""
        parent = self.parentWidget()
        if parent is None or not self.text():
            return
        width = max(parent.width() - 12, 40)
        height = min(self.heightForWidth(width), max(parent.height() // 2, 20))
        y = 30
        if self.below is not None and self.below.isVisible():
            y = self.below.geometry().bottom() + 3
        self.setGeometry(6, y, width, height)
        self.raise_()


def _fitting_number(edit: QtWidgets.QLineEdit, value: float) -> str:
    """``value`` with as many significant digits (4 down to 1) as fit in ``edit`` without clipping."""
    room = edit.contentsRect().width() - 6 if edit.width() > 0 else 10**6
    metrics = edit.fontMetrics()
    text = f"{value:.4g}"
    for digits in (4, 3, 2, 1):
        text = f"{value:.{digits}g}"
        if metrics.horizontalAdvance(text) <= room:
            return text
    return text


class _LevelsRow(QtWidgets.QWidget):
    """Typed colour range of one map: min, max, auto, symmetric about zero."""

    def __init__(self, view: "ImageView"):
        super().__init__()
        self.view = view
        row = QtWidgets.QHBoxLayout(self)
        row.setContentsMargins(2, 0, 2, 0)
        row.setSpacing(2)
        font = self.font()
        font.setPointSizeF(max(7.0, font.pointSizeF() - 1))
        self.setFont(font)
        self.min_edit = QtWidgets.QLineEdit()
        self.max_edit = QtWidgets.QLineEdit()
        for edit, what in ((self.min_edit, "lowest"), (self.max_edit, "highest")):
            edit.setMinimumWidth(34)
            edit.setMaximumWidth(80)
            edit.setToolTip(f"{what} value of the colour range ({view.units}); type a number and press Enter")
            edit.editingFinished.connect(self._typed)
        self.auto_box = QtWidgets.QCheckBox("auto")
        lo_pct, hi_pct = view.colour_rule.percentiles
        held = ", and at least what two neighbouring samples reach" if view.colour_rule.hold_features else ""
        self.auto_box.setToolTip(f"colour range follows the data (its {lo_pct:g} to {hi_pct:g} percentile{held})")
        self.auto_box.setChecked(True)
        self.symmetric_box = QtWidgets.QCheckBox("±")
        self.symmetric_box.setToolTip("colour range symmetric about zero (-m … +m)")
        self.symmetric_box.setChecked(view.symmetric)
        row.addWidget(self.min_edit, 1)
        row.addWidget(QtWidgets.QLabel("…"))
        row.addWidget(self.max_edit, 1)
        row.addWidget(self.auto_box)
        row.addWidget(self.symmetric_box)
        self.auto_box.toggled.connect(self._auto_toggled)
        self.symmetric_box.toggled.connect(self._symmetric_toggled)

    def show_levels(self, levels) -> None:
        for edit, v in ((self.min_edit, levels[0]), (self.max_edit, levels[1])):
            if not edit.hasFocus():
                edit.setText(_fitting_number(edit, v))
                edit.setStyleSheet("")

    def resizeEvent(self, ev):  # noqa: N802 - Qt's name
        super().resizeEvent(ev)
        if self.view._levels_set:  # narrower now: fewer digits, never a clipped number
            self.show_levels(self.view.levels)

    def sync(self) -> None:
        for box, value in ((self.auto_box, self.view.auto_levels), (self.symmetric_box, self.view.symmetric)):
            if box.isChecked() != value:
                box.blockSignals(True)
                box.setChecked(value)
                box.blockSignals(False)

    def _typed(self) -> None:
        edit = self.sender()
        try:
            lo, hi = float(self.min_edit.text()), float(self.max_edit.text())
        except ValueError:
            edit.setStyleSheet("border: 1px solid #c00")
            edit.setToolTip("not a number: type e.g. -1.5 or 2e-3")
            return
        if self.view.symmetric:  # the other end follows the one typed
            m = abs(lo) if edit is self.min_edit else abs(hi)
            lo, hi = -m, m
        if not hi > lo:
            edit.setStyleSheet("border: 1px solid #c00")
            edit.setToolTip("the colour range needs min < max")
            return
        edit.setStyleSheet("")
        self.view.set_levels((lo, hi))

    def _auto_toggled(self, on: bool) -> None:
        if on:
            self.view.reset_levels()
        else:
            self.view.set_levels(self.view.levels)

    def _symmetric_toggled(self, on: bool) -> None:
        self.view.set_symmetric(on)


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


#: room (px) right of a plot for the half of its bottom axis' last tick label that lies past the axis' end
#: (the "40" of a 0-40 mm profile was cut at the widget's edge at 1280x800)
LAST_TICK_ROOM_PX = 14


def room_for_the_last_tick(plot_item) -> None:
    """Leave :data:`LAST_TICK_ROOM_PX` right of ``plot_item`` so its last bottom tick label is drawn whole."""
    left, top, right, bottom = plot_item.layout.getContentsMargins()
    plot_item.layout.setContentsMargins(left, top, max(right, LAST_TICK_ROOM_PX), bottom)


class LazyMenuViewBox(pg.ViewBox):
    """A ViewBox whose right-click menu is made the first time it is opened.

    pyqtgraph makes each ViewBox's menu (a QMenu with the axis controls, 12-18 ms) when it makes the
    view: the window's 14 maps and plots made theirs at every start and camera switch's rebuild, for
    menus a session seldom opens. ``menu_actions``: ``(text, slot)`` pairs added to the menu when it
    is made. (The colour bars' plots still make theirs, which pyqtgraph switches off at once: a
    ColorBarItem put on this ViewBox lost its ViewBox's parent and drew no colours.)
    """

    def __init__(self, *args, menu_actions: Sequence = (), **kwargs):
        super().__init__(*args, enableMenu=False, **kwargs)
        self.state["enableMenu"] = True  # the menu is on: only its making waits for the first right click
        self._menu_actions = tuple(menu_actions)

    def getMenu(self, ev=None):
        if self.menu is None and self.menuEnabled():
            from pyqtgraph.graphicsItems.ViewBox.ViewBoxMenu import ViewBoxMenu

            self.menu = ViewBoxMenu(self)
            self.updateViewLists()
            for text, slot in self._menu_actions:
                self.menu.addAction(text).triggered.connect(slot)
        return self.menu

    def getContextMenus(self, event):
        menu = self.getMenu(event)
        return menu.actions() if menu is not None else []


#: the image format Qt's raster painter draws fastest (no conversion at each paint)
SCREEN_FORMAT = QtGui.QImage.Format.Format_ARGB32_Premultiplied


class ScreenImageItem(pg.ImageItem):
    """pyqtgraph's ImageItem whose rendered image is kept in premultiplied 32-bit ARGB.

    pyqtgraph renders a map through a colour table (8-bit indexed) or, where NaN samples are
    transparent, as non-premultiplied RGBA; Qt's raster painter converts either to premultiplied
    ARGB at every paint, pixel by pixel of the screen area: a 500 x 500 px tile took 0.77 ms a
    paint from an indexed image against 0.19 ms from a premultiplied one, whatever the map's size.
    Here the image is converted once, when a new map is rendered; the colours on screen are the
    same (tests/app/test_gui_usability.py). docs/gui.md has the window's figures.
    """

    def render(self):
        super().render()
        image = self.qimage
        if image is not None and image.format() != SCREEN_FORMAT:
            self.qimage = image.convertToFormat(SCREEN_FORMAT)


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


#: image types drawn as block means (camera images); others (maps) as picked samples
AVERAGED = (np.dtype(np.uint8), np.dtype(np.uint16))


def decimate_for_display(data: np.ndarray, stride: int, *, average: bool = True) -> Tuple[np.ndarray, Tuple[int, int]]:
    """``data`` with about ``1 / stride`` of its pixels each way, for a view that shows no more.

    Camera images (uint8, uint16) are averaged over ``stride`` x ``stride`` blocks (the last
    incomplete block of each side is left out), then smoothed by a [1, 2, 1] / 4 kernel over the
    blocks: picking every ``stride``-th pixel of a fine checkerboard or a random-dot image draws
    moire bands that are not on the pattern, and a pattern of about two blocks' period, which the
    block mean keeps at 64 % of its contrast, beats with any scaling Qt does afterwards; the kernel
    removes what lies that close to the blocks' Nyquist frequency (what the view cannot show
    anyway) and keeps a period of ten blocks at 90 % of its contrast (five blocks: 65 %). Maps
    (float, NaN where invalid) are smooth and keep every ``stride``-th sample, which keeps a NaN from
    spreading over its block; so do camera images with ``average=False``. Returns the data and the (rows, cols) of the full frame it covers.
    """
    if stride <= 1:
        return data, data.shape
    if average and data.dtype in AVERAGED:
        rows, cols = data.shape[0] // stride, data.shape[1] // stride
        if rows >= 3 and cols >= 3:
            block_mean = data[:rows * stride, :cols * stride]
            factor = stride
            while factor % 2 == 0:  # cv2's area interpolation halves fastest (0.1 ms at 1024^2, 0.5 for 1/5)
                block_mean = cv2.resize(block_mean, (block_mean.shape[1] // 2, block_mean.shape[0] // 2),
                                        interpolation=cv2.INTER_AREA)
                factor //= 2
            if factor > 1:  # at an integer factor, area interpolation is the block mean
                block_mean = cv2.resize(block_mean, (cols, rows), interpolation=cv2.INTER_AREA)
            # a 3 x 3 Gaussian of sigma 0 is OpenCV's fixed [1, 2, 1] / 4 kernel (0.02-0.07 ms)
            return cv2.GaussianBlur(block_mean, (3, 3), 0, borderType=cv2.BORDER_REFLECT), (rows * stride, cols * stride)
    return data[::stride, ::stride], data.shape


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
    levels_controls : bool
        Show the typed colour range row (min, max, auto, symmetric about zero) under the map.
    pan : bool
        Let a left-drag pan the view (off where the drag belongs to a line or box on the map).
    colorbar : {"horizontal", "vertical"}
        Colour bar under the map (narrow tiles: the map keeps the width) or beside it.
    colour_rule : ColourRule
        How the automatic colour range follows the data (:mod:`app.gui.model.colour_range`):
        ``CAMERA`` (1st-99th percentile: hot pixels and glints do not set the range) for camera
        images; ``SURFACE`` for the maps of the surface, where the event being watched (a disc's
        dimple, a drop) may cover a percent of the field or, at its start, a few samples: at the 99th
        percentile its core was drawn flat in the end colour (the synthetic tank's impact: a 2.4 um
        dimple under a +-0.85 um colour range).
    averaged : bool
        A camera image drawn smaller than it is is averaged and smoothed (:func:`decimate_for_display`:
        no moire, 0.3-0.6 ms a frame at 1024^2 in the GUI thread); otherwise every k-th pixel is drawn.
        On for the views where one looks at the pattern (the Alignment tab's camera image, a replayed
        frame), off for the Live tab's 60-Hz raw-frame thumbnail (there it took 4-5 % more of the GUI
        thread, and benchmarks/bench_gui.py at 1024^2 fell below 60 frames shown a second).
    """

    def __init__(self, title: str, units: str, *, cmap: str = "viridis", symmetric: bool = False,
                 axis_units: str = "mm", parent=None, levels_interval_s: float = 0.5,
                 levels_controls: bool = True, pan: bool = True, colorbar: str = "horizontal",
                 averaged: bool = False, colour_rule: ColourRule = CAMERA):
        super().__init__(parent)
        self.title = title
        self.colour_rule = colour_rule
        self.averaged = averaged
        self.units = units
        self.symmetric = symmetric
        self.auto_levels = True
        self._levels_interval_s = levels_interval_s
        self._levels_t = 0.0
        self._levels: Tuple[float, float] = (0.0, 1.0)
        self._levels_set = False
        self._rect = None
        self._drawn_shape = None  # (rows, cols) of the image last given a rect (after striding)
        self._shape = None
        self.updates = 0
        self.frame_id = None  # frame (worker sequence) of the data shown, when the caller says
        self.stale_text: Optional[str] = None
        self._user_zoomed = False
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(0)
        self.graphics = _Graphics()
        self.graphics.setBackground("w")
        self.graphics.setMinimumSize(120, 100)
        layout.addWidget(self.graphics, 1)
        self.plot = self.graphics.addPlot(viewBox=LazyMenuViewBox(
            menu_actions=(("Auto levels", self.reset_levels), ("Fit image", self.fit))))
        self._title_text: Optional[str] = None
        self.set_title(title)
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)  # row 0 at the top, like the camera image
        # The range is set explicitly (the image's rect, _refit), never by auto-range: before the first
        # data, overlays that keep their size on screen (the profile line's handles, the pin label)
        # grow in data units with the view, so auto-range grew the view to hold them, which grew them,
        # every paint: a repaint storm (views 1e111 wide, the GUI thread busy for 25 s, no frame drawn)
        # in a window restored with a reference.
        # (not enableAutoRange(False): pyqtgraph reads that False as its axis number 0, the x axis,
        # and turns x auto-range ON; the same call in ProfileView and HistogramView below did so too)
        self.plot.disableAutoRange()
        for side, name in (("bottom", "x"), ("left", "y")):
            axis = self.plot.getAxis(side)
            axis.enableAutoSIPrefix(False)
            axis.setLabel(f"{name} ({axis_units})")
            axis.setTextPen("#222")
            axis.setPen("#444")
        self.image = ScreenImageItem(axisOrder="row-major")
        # decimate by striding in set_data (pyqtgraph's auto downsample averages: ~10 ms at 1024^2)
        self.image.setAutoDownsample(False)
        self.stride = 1
        self.plot.addItem(self.image)
        cmap_obj = cmap if isinstance(cmap, pg.ColorMap) else pg.colormap.get(cmap)
        # no drag handles on the bar: the range is typed (levels row) or follows the data
        self.colorbar = pg.ColorBarItem(values=(0, 1), colorMap=cmap_obj, label=None,
                                        interactive=False, width=10, orientation=colorbar)
        self.colorbar.setImageItem(self.image, insert_in=self.plot)
        cb_axis = getattr(self.colorbar, "axis", None)
        if cb_axis is not None:
            cb_axis.setTextPen("#222")
            cb_axis.enableAutoSIPrefix(False)  # units are in the title already
        self.colorbar.sigLevelsChangeFinished.connect(self._user_levels)
        self._setting_levels = False
        vb = self.plot.getViewBox()
        vb.sigRangeChangedManually.connect(self._zoomed)
        vb.sigResized.connect(self._refit)
        if not pan:  # a left-drag never moves the view (the wheel still zooms)
            vb.mouseDragEvent = lambda ev, axis=None: ev.ignore()
        self._cache_static_items()
        # whether what is shown is old (grey, under the title) and why there is no new map (red, under
        # that): wrapped to the map's width, the full text also as tooltip
        self.stale_label = _Overlay(self.graphics, "background: rgba(235,235,235,230); color: #333;"
                                                   "font-weight: bold; padding: 2px; border: 1px solid #888;")
        self.message = _Overlay(self.graphics, "background: rgba(255,255,255,215); color: #b00000; padding: 2px;",
                                below=self.stale_label)
        self.levels_row = None
        if levels_controls:
            self.levels_row = _LevelsRow(self)
            layout.addWidget(self.levels_row)

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
        self._levels_set = False  # the next frame sets them at once
        if self.levels_row is not None:
            self.levels_row.sync()

    def set_levels(self, levels: Tuple[float, float]) -> None:
        """Fix the levels (stops auto levels)."""
        self.auto_levels = False
        if self.levels_row is not None:
            self.levels_row.sync()
        self._apply_levels(levels)
        if self.image.image is not None:
            self.image.setLevels(self._levels)

    def set_symmetric(self, symmetric: bool) -> None:
        """Colour range symmetric about zero (auto levels ``(-m, m)``; fixed levels made symmetric)."""
        self.symmetric = bool(symmetric)
        if self.levels_row is not None:
            self.levels_row.sync()
        if self.auto_levels:
            self._levels_set = False
        elif self.symmetric:
            m = max(abs(self._levels[0]), abs(self._levels[1])) or 1.0
            self.set_levels((-m, m))

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
        if self.levels_row is not None:
            self.levels_row.show_levels(self._levels)

    @property
    def levels(self) -> Tuple[float, float]:
        return self._levels

    def set_data(self, data: np.ndarray, *, x: Optional[np.ndarray] = None,
                 y: Optional[np.ndarray] = None, levels: Optional[Tuple[float, float]] = None,
                 stamp_ns: int = 0, frame_id=None) -> None:
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
        frame_id : int, optional
            Which frame the data belongs to (kept in :attr:`frame_id`; Pause and snapshots check it).
        """
        if data.dtype.kind == "f" and data.dtype != np.float32:
            data = data.astype(np.float32)
        full_shape = data.shape
        average = self.averaged and data.dtype in AVERAGED
        data, drawn_extent = decimate_for_display(data, self._stride_for(full_shape, averaged=average), average=average)
        data = np.ascontiguousarray(data)
        now = time.monotonic()
        if levels is not None:
            self._apply_levels(levels)
        elif self.auto_levels and (data.size <= 65536 or now - self._levels_t >= self._levels_interval_s
                                   or self._shape != full_shape):
            # Small (decimated) maps are checked every frame (< 1 ms), large ones a few times per second;
            # the range moves as range_moves says
            due = now - self._levels_t >= self._levels_interval_s
            new_levels = data_levels(data, self.colour_rule, symmetric=self.symmetric)
            if (self._shape != full_shape or not self._levels_set
                    or range_moves(self._levels, new_levels, due=due)):
                self._apply_levels(new_levels)
                self._levels_t = now
                if without_spread(data):  # a stand-in range: the next map with a spread sets its own at once
                    self._levels_set = False
        self.image.setImage(data, autoLevels=False, levels=self._levels)
        rect = self._rect_for(full_shape, x, y)
        # pyqtgraph scales an image to its rect when the rect is set: set it again when the
        # same area comes with another pixel count too (another stride: the view was resized)
        if rect != self._rect or data.shape != self._drawn_shape:
            x0, y0, width, height = rect  # the drawn blocks cover drawn_extent of the full frame
            self.image.setRect(QtCore.QRectF(x0, y0, width * drawn_extent[1] / full_shape[1],
                                             height * drawn_extent[0] / full_shape[0]))
            self._drawn_shape = data.shape
        if rect != self._rect:
            self._rect = rect
            self._user_zoomed = False
            self._refit()
        self._shape = full_shape
        self.frame_id = frame_id
        self.updates += 1
        if stamp_ns:
            self.graphics.pending_stamp_ns = stamp_ns

    def _stride_for(self, shape, averaged: bool = False) -> int:
        """Integer decimation so that the drawn image has about as many pixels as the view on screen:
        at least as many for maps (picked samples), at most as many for averaged camera images (Qt
        scales an image to the screen by picking pixels: shrinking averaged blocks further by up to 2x
        brought the moire back; enlarging them by up to 2x only makes them coarser)."""
        vb = self.plot.getViewBox()
        w = max(int(vb.width()), 64)
        h = max(int(vb.height()), 64)
        ratio = max(shape[0] / h, shape[1] / w) if averaged else min(shape[0] / h, shape[1] / w)
        stride = math.ceil(ratio - 1e-6) if averaged else int(ratio)
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

    def _zoomed(self, *_):
        self._user_zoomed = True

    def fit(self) -> None:
        """Show the whole image again (after a zoom)."""
        self._user_zoomed = False
        self._refit()

    def _refit(self, *_):
        """The image fills the view (aspect 1:1, no margin) unless the user zoomed."""
        if self._rect is not None and not self._user_zoomed:
            self.plot.getViewBox().setRange(QtCore.QRectF(*self._rect), padding=0.0)
        self.message.place()
        self.stale_label.place()

    def resizeEvent(self, ev):
        super().resizeEvent(ev)
        self.message.place()
        self.stale_label.place()

    def set_title(self, title: str) -> None:
        """The map's title, with its units after it (the colour bar under the map then needs no label of its own)."""
        if title == self._title_text:
            return
        self._title_text = title
        units = self.units
        self.plot.setTitle(f"<b>{title}</b> ({units})" if units else f"<b>{title}</b>", color="#111", size="10pt")

    def show_message(self, text: str, short: Optional[str] = None) -> None:
        """Overlay a (red) message, e.g. why there is no map; empty string hides it.

        ``short`` is shown instead where the tile is small; the full ``text`` is then the map's tooltip.
        """
        self.message.set_message(short if short else text)
        self.graphics.setToolTip(text if short else "")

    def set_stale(self, text: Optional[str]) -> None:
        """Mark what is shown as old (greyed, with ``text`` such as "frame 12, 2.3 s ago"); None: live again."""
        if text == self.stale_text:
            return
        self.stale_text = text
        self.image.setOpacity(0.3 if text else 1.0)
        self.stale_label.set_message(f"STALE: {text}" if text else "")
        self.message.place()

    @property
    def is_stale(self) -> bool:
        return self.stale_text is not None

    def show_paused(self, text: Optional[str]) -> None:
        """Label the view as held by Pause (e.g. "PAUSED: frame 12"); None: back to the stale mark, if any."""
        self.stale_label.set_message(text or (f"STALE: {self.stale_text}" if self.stale_text else ""))
        self.message.place()

    def current_data(self) -> Optional[np.ndarray]:
        return self.image.image


class ProfileView(QtWidgets.QWidget):
    """Height profile along a line: a plot of value vs distance along the line (mm)."""

    def __init__(self, title: str = "Profile", units: str = "height (µm)", parent=None):
        super().__init__(parent)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.plot = pg.PlotWidget(viewBox=LazyMenuViewBox())
        self.plot.setTitle(f"<b>{title}</b>", color="#111", size="10pt")
        self.plot.setBackground("w")
        self.plot.setLabel("bottom", "distance (mm)")  # along the line; short, or the column cuts the plot
        self.plot.setLabel("left", units)
        for name in ("left", "bottom"):  # already scaled (µm, mm): no SI prefix like "(x1e-06)"
            self.plot.getAxis(name).enableAutoSIPrefix(False)
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        self.curve = self.plot.plot(pen=pg.mkPen("#1f77b4", width=2))
        self.plot.disableAutoRange()  # ranges set explicitly: axes are not redrawn every frame
        _cache_axes(self.plot.getPlotItem())
        room_for_the_last_tick(self.plot.getPlotItem())
        self._range = None
        self._range_t = 0.0
        self.frame_id = None
        self.stale_text = None
        layout.addWidget(self.plot)
        self.stale_label = _Overlay(self.plot, "background: rgba(235,235,235,230); color: #333;"
                                               "font-weight: bold; padding: 2px; border: 1px solid #888;")

    def set_stale(self, text: Optional[str]) -> None:
        """Grey the curve and label it (e.g. "frame 12, 2.3 s ago"); None: live again."""
        if text == self.stale_text:
            return
        self.stale_text = text
        self.curve.setOpacity(0.3 if text else 1.0)
        self.stale_label.set_message(f"STALE: {text}" if text else "")

    def show_paused(self, text: Optional[str]) -> None:
        """Label the plot as held by Pause; None: back to the stale mark, if any."""
        self.stale_label.set_message(text or (f"STALE: {self.stale_text}" if self.stale_text else ""))

    def resizeEvent(self, ev):
        super().resizeEvent(ev)
        self.stale_label.place()

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
        self.plot = pg.PlotWidget(viewBox=LazyMenuViewBox())
        self.plot.setBackground("w")
        self.plot.setLabel("bottom", "pixel value")
        self.plot.setLabel("left", "pixels (log10)")
        self.plot.setMaximumHeight(150)
        self.plot.setMinimumHeight(90)
        self.curve = self.plot.plot(stepMode="center", fillLevel=0, brush=(80, 80, 200, 120),
                                    pen=pg.mkPen("#3040a0"))
        self.plot.disableAutoRange()
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
        title = f"<b>Histogram</b> {saturation_pct:.2f} % saturated"
        if title != self._title:
            self.plot.setTitle(title, color="#b00000" if saturation_pct > 0.5 else "#222", size="10pt")
            self._title = title


class SpectrumView(ImageView):
    """Log-magnitude spectrum with the detected carrier peaks marked."""

    def __init__(self, parent=None):
        super().__init__("Spectrum", "log10 |FFT|", cmap="inferno", axis_units="cycles/px",
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


class ProfileLine(pg.LineSegmentROI):
    """The profile line on a map: drag an end handle to move that end, the body to move the whole line.

    The body can be grabbed within ``grab_px`` screen pixels of the line; the
    view under it never pans (its ImageView is made with ``pan=False``).
    """

    def __init__(self, positions, *, grab_px: float = 8.0, colour: str = "#ff00ff"):
        super().__init__(positions, pen=pg.mkPen(colour, width=2), hoverPen=pg.mkPen("#ffb0ff", width=3),
                         handlePen=pg.mkPen(colour, width=2), handleHoverPen=pg.mkPen("#ffb0ff", width=3))
        self.grab_px = float(grab_px)
        for h in self.getHandles():
            h.radius = 7  # end handles big enough to hit
            h.buildPath()
        self.setZValue(20)
        self.setToolTip("profile line: drag an end to move it, the line to move both ends")

    def set_ends(self, p0, p1) -> None:
        """Put the ends at ``p0``, ``p1`` (map coordinates, mm), as a drag would (the ROI's state follows)."""
        h0, h1 = self.getHandles()[:2]
        self.movePoint(h0, QtCore.QPointF(*p0), finish=False)
        self.movePoint(h1, QtCore.QPointF(*p1))

    def ends(self):
        """``((x0, y0), (x1, y1))`` of the ends in the map's coordinates (mm)."""
        pts = [self.mapToParent(h.pos()) for h in self.getHandles()[:2]]
        return (pts[0].x(), pts[0].y()), (pts[1].x(), pts[1].y())

    def shape(self):
        p = QtGui.QPainterPath()
        h1 = self.endpoints[0].pos()
        h2 = self.endpoints[1].pos()
        dh = h2 - h1
        if dh.length() == 0:
            return p
        pxv = self.pixelVectors(dh)[1]
        if pxv is None:
            return p
        pxv *= self.grab_px
        p.moveTo(h1 + pxv)
        p.lineTo(h2 + pxv)
        p.lineTo(h2 - pxv)
        p.lineTo(h1 - pxv)
        p.lineTo(h1 + pxv)
        return p
