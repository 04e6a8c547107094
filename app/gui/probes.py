"""Live probes: wave gauges you place on the height map and move while the water moves.

Click on the Live height map to place a probe at that surface point (mm);
drag its marker to move it (its series starts again there), right-click it to
remove it. Each drawn Result adds one value per probe, read at the probe's
``(x_mm, y_mm)`` with the bilinear rule of :mod:`processing.probe` (the one
``tirdeflect probe`` uses on OUT.h5). The small plot under the profile shows
the last :data:`HISTORY_S` seconds; only the newest points are appended.
"""

from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore, QtWidgets

from processing.errors import TirdeflectError
from processing.probe import probe_cell, sample_cell

from .views import LazyMenuViewBox, room_for_the_last_tick

__all__ = ["Probe", "ProbeView", "HISTORY_S", "MAX_PROBES"]

#: seconds of history a probe keeps and shows
HISTORY_S = 30.0
#: most probes at once (each has its own colour)
MAX_PROBES = 6
_COLOURS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")


class _Marker(pg.TargetItem):
    """A probe's marker: drag to move, right-click to remove."""

    def __init__(self, probe: "Probe", colour: str):
        super().__init__(pos=(probe.x_mm, probe.y_mm), size=14, symbol="crosshair", movable=True,
                         pen=pg.mkPen(colour, width=2), label=probe.label,
                         labelOpts={"color": colour, "offset": (8, -4)})
        self.probe = probe
        self.setZValue(30)

    def mouseClickEvent(self, ev):
        if ev.button() == QtCore.Qt.RightButton:
            ev.accept()
            self.probe.owner.remove(self.probe)
            return
        super().mouseClickEvent(ev)


class Probe:
    """One gauge: position (mm), bounded series of (time s, height um)."""

    def __init__(self, owner: "ProbeView", number: int, x_mm: float, y_mm: float, colour: str):
        self.owner, self.number, self.colour = owner, number, colour
        self.x_mm, self.y_mm = float(x_mm), float(y_mm)
        self.times_s: deque = deque()
        self.heights_um: deque = deque()
        self.seqs: deque = deque()  # the processed frame each value came from
        self._cell = None  # grid cell cache: (grid key, cell)
        self.marker = _Marker(self, colour)
        self.marker.sigPositionChangeFinished.connect(self._moved)
        self.curve = owner.plot.plot(pen=pg.mkPen(colour, width=2), name=self.label)

    @property
    def label(self) -> str:
        return f"P{self.number}"

    def _moved(self, *_):
        pos = self.marker.pos()
        self.move_to(pos.x(), pos.y())

    def move_to(self, x_mm: float, y_mm: float) -> None:
        """Put the gauge at ``(x_mm, y_mm)``; its series starts again (a gauge measures where it is)."""
        self.x_mm, self.y_mm = float(x_mm), float(y_mm)
        self._cell = None
        self.times_s.clear()
        self.heights_um.clear()
        self.seqs.clear()
        self.marker.setPos(self.x_mm, self.y_mm)
        self.curve.setData([], [])

    def add(self, result, t_s: float, seq: int) -> Optional[float]:
        """Height (um) of ``result`` at the probe (NaN outside the field or unmeasured), appended at ``t_s``."""
        key = (result.x_mm.size, result.y_mm.size, float(result.x_mm[0]), float(result.y_mm[0]),
               float(result.x_mm[-1]), float(result.y_mm[-1]))
        if self._cell is None or self._cell[0] != key:
            try:
                self._cell = (key, probe_cell(result.x_mm, result.y_mm, self.x_mm, self.y_mm))
            except TirdeflectError:
                self._cell = (key, None)
        cell = self._cell[1]
        value = float("nan") if cell is None else 1e3 * sample_cell(result.height, cell)
        self.times_s.append(float(t_s))
        self.heights_um.append(value)
        self.seqs.append(int(seq))
        while self.times_s and self.times_s[0] < t_s - HISTORY_S:
            self.times_s.popleft()
            self.heights_um.popleft()
            self.seqs.popleft()
        return value


class ProbeView(QtWidgets.QWidget):
    """The probes' time-series plot; places probes on ``map_plot`` (the height map's PlotItem, mm)."""

    def __init__(self, map_plot: pg.PlotItem, parent=None):
        super().__init__(parent)
        self.map_plot = map_plot
        self.probes: list = []
        self._numbers = 0
        self._t0_ns: Optional[int] = None
        self.plot = pg.PlotWidget(viewBox=LazyMenuViewBox())
        self.plot.setBackground("w")
        self.plot.setLabel("bottom", "time (s)")
        self.plot.setLabel("left", "height (µm)")
        self.plot.getAxis("left").enableAutoSIPrefix(False)  # already in µm: no "(x1e-06)"
        self.stale_text = None
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        # the probes' colours are named in the title, never in a legend box over the series
        self._show_title()
        room_for_the_last_tick(self.plot.getPlotItem())
        self._hint = ("Click the height map to place a probe; drag it to move it, right-click it to "
                      "remove it. Last %d s." % HISTORY_S)
        self.plot.setToolTip(self._hint)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.plot)
        map_plot.scene().sigMouseClicked.connect(self._clicked)

    def set_stale(self, text) -> None:
        """Grey the series and say so in the title while the maps they come from are stale; None: live."""
        if text == self.stale_text:
            return
        self.stale_text = text
        self._show_title()
        self.plot.setToolTip(f"STALE: {text}" if text else self._hint)
        for probe in self.probes:
            probe.curve.setOpacity(0.3 if text else 1.0)

    def _show_title(self) -> None:
        """"Probes", STALE while the maps are, and each probe's name in its curve's colour (a few words:
        1280x800's column holds them)."""
        parts = ["<b>Probes</b>"]
        if self.stale_text is not None:
            parts.append("<span style='color:#a00'>STALE</span>")
        if self.probes:
            parts += [f"<span style='color:{p.colour}'>&#9472; {p.label}</span>" for p in self.probes]
        else:
            parts.append("(click the map)")
        self.plot.setTitle(" ".join(parts), color="#111", size="10pt")

    def _clicked(self, ev):
        if ev.button() != QtCore.Qt.LeftButton or ev.isAccepted() or ev.double():
            return
        vb = self.map_plot.getViewBox()
        if not vb.sceneBoundingRect().contains(ev.scenePos()):
            return
        p = vb.mapSceneToView(ev.scenePos())
        self.add(p.x(), p.y())

    def add(self, x_mm: float, y_mm: float) -> Probe:
        """Place a probe at ``(x_mm, y_mm)`` (the oldest goes when there are :data:`MAX_PROBES`)."""
        if len(self.probes) >= MAX_PROBES:
            self.remove(self.probes[0])
        self._numbers += 1
        probe = Probe(self, self._numbers, x_mm, y_mm, _COLOURS[(self._numbers - 1) % len(_COLOURS)])
        self.map_plot.addItem(probe.marker)
        self.probes.append(probe)
        self._show_title()
        return probe

    def remove(self, probe: Probe) -> None:
        if probe in self.probes:
            self.probes.remove(probe)
            self.map_plot.removeItem(probe.marker)
            self.plot.removeItem(probe.curve)
            self._show_title()

    def clear(self) -> None:
        for probe in list(self.probes):
            self.remove(probe)

    def update(self, processed) -> None:
        """Append the newest drawn Result (``Processed`` of the live worker) to every probe's series."""
        r = getattr(processed, "result", None)
        if r is None or not self.probes:
            return
        ns = int(processed.host_timestamp_ns or 0)
        if self._t0_ns is None:
            self._t0_ns = ns
        t_s = (ns - self._t0_ns) * 1e-9
        for probe in self.probes:
            probe.add(r, t_s, processed.seq)
            probe.curve.setData(np.fromiter(probe.times_s, float), np.fromiter(probe.heights_um, float),
                                connect="finite")
