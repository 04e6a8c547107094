"""The reference region the height offset is pinned on, drawn on the raw view.

The Reconstructor chooses the region once from the reference
(``Reconstructor.reference_region`` on its decimated grid: the user's box
where the reference shows the pattern, or by default the border band of the
reference's valid area). This overlay tints it green and labels it with the
fraction of it valid in the newest frame (``Result.pin``), or where the
reference is valid until a frame arrives; red when the pin fell back to the
samples nearest the region, the pattern moved in the user's region (a surface
not at rest, or a camera or board that moved: ``PinStatus.still``), the whole
pattern shifted alike (the water level changed, or the camera or the board
moved: ``PinStatus.shifted``), the frame shows bands of light along its rows or a vignette
(:class:`processing.banding.LightBands`: "LIGHT BANDS", "VIGNETTING") or jumps against the previous one.
Green with "band moving" where the pattern moved on the default border band (TIR:
:func:`processing.pin.band_moved`, what ``tirdeflect process`` says of such frames): no fault of
the frame, but the heights' tilt is then set by that band.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore

from processing.pin import band_moved

from .views import ScreenImageItem

_LUT_OK = np.array([[0, 0, 0, 0], [0, 200, 0, 90]], np.uint8)
_LUT_BAD = np.array([[0, 0, 0, 0], [220, 0, 0, 110]], np.uint8)


class PinRegionOverlay:
    """Green tint of the reference region on a pixel-coordinate plot, plus a label.

    The label on the image is a few words ("h = 0: 100 % valid"): the raw view is 140-220 px wide at
    1280x800-1600x1000, and the whole sentence (:attr:`text`, also the label's tooltip) ran past its
    edge. When the pin is in trouble (red), the whole sentence goes to ``note`` (the raw view's wrapped
    message), where it can be read.

    Parameters
    ----------
    plot : pyqtgraph PlotItem or ViewBox
        The raw view's plot (coordinates in pixels: x = column, y = row).
    note : callable, optional
        ``note(text)`` shows why the pin is red (``""``: nothing to say any more).
    """

    def __init__(self, plot, note=None):
        self.image = ScreenImageItem(axisOrder="row-major")
        self.image.setLookupTable(_LUT_OK)
        self.image.setZValue(15)
        # anchored by a lower corner on the region's last row: drawn above it, inside the frame (below the
        # border band it would fall outside the view); by its right corner when the region lies to the right
        self.label = pg.TextItem("", color="#00a000", anchor=(0, 1), fill=pg.mkBrush(255, 255, 255, 210))  # readable on the pattern
        self.label.setZValue(21)
        plot.addItem(self.image)
        plot.addItem(self.label)
        self.note = note
        self.name = ""
        self.setup = ""
        self.samples = 0
        self.text = ""
        self.short = ""
        self.bad = False
        self.stale = False  # the maps the label was measured on are not the live frame's (model/staleness.py)
        self.set_reconstructor(None)

    def set_reconstructor(self, rec) -> None:
        """Show the region of ``rec`` (None hides it)."""
        region = getattr(rec, "reference_region", None)
        if region is None:
            self.image.setVisible(False)
            self.label.setVisible(False)
            self.text = self.short = ""
            if self.bad and self.note is not None:
                self.note("")
            self.bad = False
            return
        rows, cols = np.asarray(rec.rows_px, float), np.asarray(rec.cols_px, float)
        dr = rows[1] - rows[0] if rows.size > 1 else 1.0
        dc = cols[1] - cols[0] if cols.size > 1 else 1.0
        self.image.setImage(np.ascontiguousarray(region, dtype=np.uint8), autoLevels=False, levels=(0, 1))
        self.image.setRect(QtCore.QRectF(cols[0] - dc / 2, rows[0] - dr / 2, dc * cols.size, dr * rows.size))
        self.name = rec.reference_region_name
        self.setup = getattr(getattr(rec, "geometry", None), "setup", "")  # band_moved judges TIR only
        self.samples = int(np.count_nonzero(region))
        r, c = np.nonzero(region)
        if r.size:
            left, right = float(cols[c.min()] - dc / 2), float(cols[c.max()] + dc / 2)
            mid = float(cols[0] + cols[-1]) / 2
            on_right = (left + right) / 2 > mid and left > cols[0] + 0.25 * (cols[-1] - cols[0])
            # a box: the label above it, or below it, where the frame has room (about 15 % of its height at
            # 1280x800), so that it does not hide the box; the border band: inside, above its last row
            top, bottom = float(rows[r.min()] - dr / 2), float(rows[r.max()] + dr / 2)
            span = float(rows[-1] - rows[0]) + dr
            if top - (rows[0] - dr / 2) > 0.15 * span:
                y, ay = top, 1
            elif (rows[-1] + dr / 2) - bottom > 0.15 * span:
                y, ay = bottom, 0
            else:
                y, ay = float(rows[r.max()] - dr), 1
            self.label.setAnchor((1 if on_right else 0, ay))
            self.label.setPos(right if on_right else left, y)
        pct = 100 * rec.reference_region_valid_fraction
        self._show(f"{self.name} (h = 0): {pct:.0f} % valid in the reference, {self.samples} samples",
                   f"h = 0: {pct:.0f} % valid", bad=self.samples == 0)

    def update(self, result, light_bands=None) -> None:
        """Label the region with the fraction of it valid in ``result`` (a Result), and what is wrong with
        the frame's heights; ``light_bands``: the live frame's :class:`processing.banding.LightBands`."""
        pin = getattr(result, "pin", None)
        if pin is None or not self.name:
            return
        frac = pin.valid_samples / pin.region_samples if pin.region_samples else 0.0
        text = f"{self.name} (h = 0): {100 * frac:.0f} % valid"
        flags = []  # the label's words for what is wrong; the tooltip and the raw view's message say why
        words = []  # words to know that are no fault (the label stays green)
        if not pin.ok:
            text += f" — too few, pinned on the {pin.used_samples} nearest valid samples"
            flags.append("too few")
        if pin.shifted:  # the whole frame moved alike: says more than the region's motion, which it explains
            text += " — " + pin.shift_text()
            flags.append("SHIFTED")
        elif not pin.still:
            text += (f" — the pattern MOVED here by {pin.region_motion_px:.2g} px since the reference: the surface "
                     "here is not at rest, or the camera or the board moved (the heights carry a tilt)")
            flags.append("MOVED")
        elif band_moved(pin.region, pin.rule, pin.region_motion_px, self.setup):
            # what `tirdeflect process` says of such frames (frames_pin_band_moving); not red: waves that fill
            # the frame move the default band in every frame of a sound recording, but its tilt is the band's
            text += (f" — the pattern moved on this band by {pin.region_motion_px:.2g} px (waves reaching it, or "
                     "the camera or the board moved): it sets the heights' tilt; give a reference region on water at "
                     "rest (Geometry) for h = 0")
            words.append("band moving")
        if pin.scaled:  # the image's scale changed: a refocus or the camera moved along its axis
            text += " — " + pin.scale_text()
            flags.append("SCALE CHANGED")
        turn = getattr(result, "turn", None)
        if turn is not None and turn.flagged:
            text += (f" — the pattern TURNED by {abs(turn.turn_mrad):.2f} mrad since the reference (camera or board "
                     f"moved{'; taken out of the heights' if turn.removed else ''}): capture a new reference")
            flags.append("TURNED")
        if light_bands is not None and light_bands.named:  # bands (evened out before measuring or not), a vignette
            flag = "LIGHT BANDS" if light_bands.flagged else "VIGNETTING"  # (bands on a vignette: both said)
            text += f" — {flag}: " + light_bands.describe()
            flags.append(flag)
        series = getattr(result, "series", None)
        if series is not None and series.flagged:
            text += " — JUMP against the previous frame"
            flags.append("JUMP")
        # a few words on a raw view that may be 150 px wide: "100 % valid" says nothing beside a flag
        valid = [] if flags and frac >= 1.0 else [f"{100 * frac:.0f} % valid"]
        short = "h = 0: " + ", ".join(valid + flags + words)
        bad = bool(flags)
        self._show(text, short, bad=bad)

    def set_stale(self, stale: bool) -> None:
        """The maps on screen are ``stale`` (another camera's, a lost camera's, older than the frames): the
        label on the live raw frame says so in grey rather than the old maps' "100 % valid" in green. After a
        switch from the synthetic camera to the GigE camera, the reference's green "h = 0: 100 % valid" stood
        on the new camera's frames, which nothing measured (by-hand trial, 7 Dec 2026)."""
        stale = bool(stale) and bool(self.short)
        if stale == self.stale:
            return
        self.stale = stale
        if stale:
            self.label.setText("h = 0: no live maps", color="#808080")
            self.label.setToolTip(f"{self.text} (of maps that are not the live frame's: see the Height map)")
        else:
            self.label.setText(self.short, color="#d00000" if self.bad else "#00a000")
            self.label.setToolTip(self.text)

    def _show(self, text: str, short: str, *, bad: bool) -> None:
        if self.stale:  # maps of a live frame are drawn: the label is theirs again
            self.stale = False
            self.text = ""
        if text != self.text or bad != self.bad or short != self.short:
            was_bad = self.bad
            self.text, self.short, self.bad = text, short, bad
            self.label.setText(short, color="#d00000" if bad else "#00a000")
            self.label.setToolTip(text)
            self.image.setLookupTable(_LUT_BAD if bad else _LUT_OK)
            if self.note is not None and (bad or was_bad):
                self.note(f"height offset: {text}" if bad else "")
        self.image.setVisible(self.samples > 0)
        self.label.setVisible(True)
