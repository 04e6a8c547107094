"""When the window draws, what the replay tab processes next, and rates that fall to 0.

Pure state machines over a clock passed in (seconds, ``time.perf_counter``/``time.monotonic``), so
their rules are tested without a window or a timer.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, Hashable, Optional, Tuple

__all__ = ["DISPLAY_MAX_HZ", "MAPS_MAX_HZ", "MAPS_WHOLE_MAX_FRACTION", "EARLY_MIN_WAIT", "RAW_RETRY_FRACTION",
           "LIVE_TAB", "ALIGNMENT_TAB", "TickPlan", "DrawClock", "RateCounter", "LiveRates", "ReplayQueue",
           "REPLAY_REST_S", "ExportProgress", "timer_ms"]

DISPLAY_MAX_HZ = 60.0  # the raw camera view refreshes at most this often
MAPS_MAX_HZ = 60.0  # processed maps at most this often (and never more than one result per display tick)
# A result's maps are drawn in one tick while that took at most this fraction of a display period (the
# decimated maps of a 512^2 camera: 2-2.5 ms of 16.7; of 1024^2 about 6 ms, at the limit: measured in the
# window by benchmarks/bench_gui.py); slower, they go in two halves on consecutive ticks, so that no tick
# is long enough to make the raw view miss its cadence
MAPS_WHOLE_MAX_FRACTION = 0.35
# A result that arrives between two ticks is drawn at once (DrawClock.plan_early) when the next tick is at
# least this fraction of a display period away, after its drawing too; else it waits for the tick
EARLY_MIN_WAIT = 0.25
# A tick of a camera tab that found no camera frame newer than the one on screen looks again this fraction of a
# display period later, once (DrawClock.retry_s): frames reach the ring in bursts (the synthetic camera at 100 Hz
# left 2.4 of 60 ticks a second without a newer frame at 1024^2 beside the window's other threads, 7 Dec 2026), and
# a frame that comes just after a tick is then shown a few ms late instead of a whole period later
RAW_RETRY_FRACTION = 0.25
LIVE_TAB, ALIGNMENT_TAB = 0, 1  # the tabs that show the camera (the window's tab indices)


@dataclasses.dataclass(frozen=True)
class TickPlan:
    """What one display tick draws: ``raw`` the newest camera frame; ``maps`` None, ``"all"`` (every map of
    ``result``), ``"first half"`` (height, profile, mask, probes of ``result``), ``"second half"``
    (displacement, slopes of ``result``, whose first half was drawn on the tick before) or ``"alignment"``
    (the Alignment tab's views of ``result``)."""

    raw: bool = False
    maps: Optional[str] = None
    result: Any = None


def timer_ms(seconds: float) -> int:
    """The display timer's interval (ms, at least 1) for a wait of ``seconds``: what every re-arming of it uses."""
    return max(1, int(round(1e3 * seconds)))


@dataclasses.dataclass
class DrawClock:
    """The display cadence: raw frames at <= ``display_hz``, maps at <= ``maps_hz``.

    :meth:`tick` is called at each display tick and returns the wait until the next one (s): the next
    tick is due one period after this one was due (drawing time does not stretch the period), and a
    tick more than a period late restarts the cadence from now (late ticks never pile up); ``ticks_lost``
    counts the ticks so skipped (the display thread was busy or starved: benchmarks/bench_gui.py).
    A result's maps are drawn in one tick while drawing them all took at most ``whole_max_fraction`` of
    a display period (:meth:`maps_took` is told each drawing's seconds; ``maps_draw_s`` is their running
    estimate), else in two halves on consecutive ticks (:meth:`take_second_half`), so each tick stays
    short and the raw view keeps its cadence.
    """

    display_hz: float = DISPLAY_MAX_HZ
    maps_hz: float = MAPS_MAX_HZ
    whole_max_fraction: float = MAPS_WHOLE_MAX_FRACTION
    maps_draw_s: float = 0.0  # running estimate of the seconds drawing one result's maps takes (0: none yet)
    first_half_s: float = 0.0  # the first half's seconds, until its second half is drawn
    next_due: Optional[float] = None
    maps_t: float = float("-inf")
    second_half: Any = None
    ticks_lost: int = 0
    last_raw_seq: int = -1  # the camera frame on screen (-1: none yet)
    raw_retry: bool = False  # the last tick of a camera tab found no newer camera frame (retry_s looks again)
    last_result_seq: int = -1  # the worker's result whose maps were last begun (-1: none yet)

    def tick(self, now: float) -> float:
        period = 1.0 / self.display_hz
        due = (now if self.next_due is None else self.next_due) + period
        if due < now - period:
            self.ticks_lost += int((now - due) / period + 1e-9)
            due = now
        self.next_due = due
        return due - now

    def wait_s(self, now: float) -> float:
        """Seconds from ``now`` to the tick due (after the drawing of this tick)."""
        return (self.next_due if self.next_due is not None else now) - now

    def maps_due(self, now: float) -> bool:
        """True if maps may be begun at ``now``: ``1 / maps_hz`` after the last, less half a display period
        (ticks come a little early or late; at ``maps_hz == display_hz`` every tick may draw maps)."""
        return now - self.maps_t >= 1.0 / self.maps_hz - 0.5 / self.display_hz

    def whole_maps(self) -> bool:
        """True if the next result's maps go in one tick (their drawing is short enough)."""
        return self.maps_draw_s <= self.whole_max_fraction / self.display_hz

    def maps_took(self, part: str, seconds: float) -> None:
        """The drawing of ``part`` (a :class:`TickPlan` ``maps``: "all", "first half" or "second half")
        took ``seconds``; the estimate follows the newest drawings (a quarter weight each)."""
        if part == "first half":
            self.first_half_s = float(seconds)
            return
        if part == "second half":
            seconds, self.first_half_s = self.first_half_s + float(seconds), 0.0
        elif part != "all":
            return
        self.maps_draw_s = float(seconds) if self.maps_draw_s == 0.0 else 0.75 * self.maps_draw_s + 0.25 * seconds

    def maps_drawn(self, now: float, result) -> None:
        """Maps were begun at ``now``; ``result`` (None: nothing left) has its second half drawn on the next tick."""
        self.maps_t = now
        self.second_half = result

    def take_second_half(self):
        pending, self.second_half = self.second_half, None
        return pending

    def plan(self, now: float, tab: int, raw_seq: Optional[int], result) -> TickPlan:
        """What to draw on this tick, and noted as drawn: ``raw_seq`` the newest camera frame's number (None:
        none), ``result`` the worker's newest (anything with ``seq``; None: none) on tab ``tab``.

        A new camera frame is drawn on every tick of the Live and Alignment tabs; maps at <= ``maps_hz``:
        the second half of the result begun on the tick before (Live tab) comes first, else a result not
        drawn yet (Live: all its maps, or its first half when drawing them all is slow, :meth:`whole_maps`;
        Alignment: its alignment views).
        """
        camera_tab = tab in (LIVE_TAB, ALIGNMENT_TAB)
        raw = camera_tab and raw_seq is not None and raw_seq != self.last_raw_seq
        self.raw_retry = camera_tab and raw_seq is not None and not raw
        if raw:
            self.last_raw_seq = raw_seq
        pending = self.take_second_half()
        if pending is not None and tab == LIVE_TAB:
            return TickPlan(raw, "second half", pending)
        if result is None or result.seq == self.last_result_seq or not camera_tab or not self.maps_due(now):
            return TickPlan(raw)
        return self._begin_maps(now, tab, raw, result)

    def retry_s(self, now: float) -> Optional[float]:
        """After a tick: seconds from ``now`` to one look again for a late camera frame (:data:`RAW_RETRY_FRACTION`
        of a period), where the tick found none newer than the one on screen and the next tick is more than twice
        that away; else None.  Once a tick: the look again (:meth:`plan_retry`) is not a tick of the cadence."""
        wait = RAW_RETRY_FRACTION / self.display_hz
        retry, self.raw_retry = self.raw_retry, False
        return wait if retry and self.wait_s(now) > 2 * wait else None

    def plan_retry(self, raw_seq: Optional[int]) -> bool:
        """The look again: True, and noted as drawn, when camera frame ``raw_seq`` (None: none) is newer than the
        one on screen; no maps (they keep the ticks' schedule)."""
        if raw_seq is None or raw_seq == self.last_raw_seq:
            return False
        self.last_raw_seq = raw_seq
        return True

    def _begin_maps(self, now: float, tab: int, raw: bool, result) -> TickPlan:
        self.last_result_seq = result.seq
        if tab != LIVE_TAB:
            self.maps_drawn(now, None)
            return TickPlan(raw, "alignment", result)
        if self.whole_maps():
            self.maps_drawn(now, None)
            return TickPlan(raw, "all", result)
        self.maps_drawn(now, result)
        return TickPlan(raw, "first half", result)

    def plan_early(self, now: float, tab: int, result, to_tick_s: float) -> TickPlan:
        """Maps of a result that has just arrived, drawn between two ticks: ``to_tick_s`` is the wait to the next
        tick (s). Waiting for it would add on average half a display period to the height map's latency (8 ms
        at 60 Hz: a sixth of the live latency at 1024^2, benchmarks/bench_gui.py), so the Live tab's maps (all,
        or the first half) are drawn at once when the next tick is at least ``EARLY_MIN_WAIT`` of a period away
        and their drawing (the running estimate) ends before it with that much to spare; the rules of
        :meth:`plan` otherwise hold (a result drawn once, its second half on the next tick), and a whole
        ``1 / maps_hz`` since the last maps: :meth:`maps_due`'s half period of slack is for ticks that come a
        little early or late; an early draw given it too drew 68-80 results a second beside 60 Hz ticks with
        results at 100 Hz (soak trial, 8 Dec 2026), more than the screen shows.
        No camera frame is drawn early: the raw view keeps the tick's cadence."""
        period = 1.0 / self.display_hz
        draw_s = self.maps_draw_s if self.whole_maps() else self.maps_draw_s / 2
        if (tab != LIVE_TAB or result is None or result.seq == self.last_result_seq or self.second_half is not None
                or now - self.maps_t < 1.0 / self.maps_hz or to_tick_s - draw_s < EARLY_MIN_WAIT * period):
            return TickPlan()
        return self._begin_maps(now, tab, False, result)


@dataclasses.dataclass
class RateCounter:
    """Events per second, measured over each whole second (the status bar's "shown" frames per second)."""

    rate: float = 0.0
    count: int = 0
    since: Optional[float] = None

    def add(self, now: float, n: int = 1) -> float:
        """Count ``n`` events at ``now``; returns the rate of the last whole second."""
        if self.since is None:
            self.since = now
        self.count += n
        if now - self.since >= 1.0:
            self.rate = self.count / (now - self.since)
            self.count, self.since = 0, now
        return self.rate


@dataclasses.dataclass
class LiveRates:
    """A measured rate while its counter keeps changing, 0 once it has not changed for ``stale_after_s``."""

    stale_after_s: float = 1.0
    last: Dict[Hashable, Tuple[Any, float]] = dataclasses.field(default_factory=dict)

    def rate(self, key: Hashable, counter, measured: float, now: float) -> float:
        last = self.last.get(key)
        if last is None or last[0] != counter:
            self.last[key] = (counter, now)
            return float(measured) if last is not None else 0.0
        return float(measured) if now - last[1] < self.stale_after_s else 0.0


#: Seconds the Replay slider rests on a frame before it is measured on every pixel (:class:`ReplayQueue`).
REPLAY_REST_S = 0.4


@dataclasses.dataclass
class ReplayQueue:
    """The replay frame to reconstruct next, and on which grid: only the newest request is kept (sliders move
    fast) and measured on the live (decimated) grid at once; once that is shown and the slider has rested
    :data:`REPLAY_REST_S` on it, the same frame on every pixel, as ``tirdeflect process`` and the export measure
    it (the live grid's heights of a 256^2 frame differ from those by 1.7-2.4 % RMS; 7 Dec 2026)."""

    wanted: Optional[Tuple[Any, int]] = None
    #: ``(frame, index, due)``: the frame shown on the live grid, to measure on every pixel from ``due`` on
    full: Optional[Tuple[Any, int, float]] = None
    rest_s: float = REPLAY_REST_S

    def want(self, frame, index: int) -> None:
        self.wanted = (frame, int(index))
        self.full = None

    def take(self, ready: bool, now: float = 0.0) -> Optional[Tuple[Any, int, str]]:
        """``(frame, index, grid)`` to run now (None: none, ``ready`` False (a running job takes it when it
        ends), or the frame's every-pixel turn not due yet: :meth:`due_in_s`)."""
        if not ready:
            return None
        if self.wanted is not None:
            (frame, index), self.wanted = self.wanted, None
            return frame, index, "decimated"
        if self.full is not None and now >= self.full[2]:
            (frame, index, _), self.full = self.full, None
            return frame, index, "full"
        return None

    def measured(self, frame, index: int, grid: str, now: float) -> None:
        """The frame ``index`` was measured on ``grid``: after the live grid, its every-pixel turn is due
        :attr:`rest_s` from ``now`` unless another frame is wanted meanwhile."""
        if grid == "decimated" and self.wanted is None:
            self.full = (frame, int(index), now + self.rest_s)

    def due_in_s(self, now: float) -> Optional[float]:
        """Seconds until the every-pixel measurement is due (None: none waits)."""
        return None if self.full is None or self.wanted is not None else max(0.0, self.full[2] - now)


@dataclasses.dataclass
class ExportProgress:
    """A replay export: ``state`` idle, running, done or error; ``fraction`` done; ``result`` once ended."""

    state: str = "idle"
    fraction: float = 0.0
    result: Optional[tuple] = None

    def start(self) -> None:
        self.state, self.fraction, self.result = "running", 0.0, None

    def progress(self, done: int, total: int) -> None:
        self.fraction = done / max(total, 1)

    def finish(self, result: tuple) -> None:
        self.state = result[0]
        if result[0] == "done":
            self.fraction = 1.0
        self.result = result
