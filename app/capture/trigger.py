"""Triggered capture: N frames before and M frames after a trigger, every frame on disk.

Frame indices are counted from the trigger frame: ``-pre .. -1`` are the
pre-trigger frames, ``0 .. post-1`` the trigger frame and those after it
(``/frame_table["trigger_index"]`` in the file; the trigger frame carries
``FrameFlags.TRIGGER``).

Trigger sources (``TRIGGER_SOURCES``):

``software``
    The camera runs free; :meth:`TriggeredCapture.trigger_now` (GUI button,
    CLI) makes the newest frame in the ring the trigger frame.
``genicam``
    The camera is in ``trigger_mode="On"``, ``trigger_source="Software"`` and
    makes one frame per GenICam ``TriggerSoftware`` command, which the camera
    thread sends once per frame period
    (:meth:`Acquisition.set_software_trigger_rate`); the capture trigger is
    then given as for ``software``.
``line0`` .. ``line3``
    Hardware line: ``trigger_mode="On"``, ``trigger_source="LineN"`` and the
    activation edge are written to the camera and read back
    (:func:`configure_trigger`). Each line pulse makes one frame, so the frames
    only exist once the line fires: index 0 is the first frame after arming
    (``pre`` must be 0). Not testable without a pulse source: on the fake
    camera only the configuration read-back is exercised.
``auto``
    :class:`AutoTrigger`, fed with slope maps by the processing worker, fires
    when the RMS slope in a region exceeds a threshold; the trigger frame is
    the frame whose slopes crossed it.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Callable, Optional, Tuple

import numpy as np

from drivers.base import CameraSettings, FrameFlags, SettingError

from .recorder import Recorder, RecorderError

__all__ = [
    "TRIGGER_SOURCES",
    "TriggerError",
    "configure_trigger",
    "frames_for_seconds",
    "AutoTrigger",
    "TriggeredCapture",
    "rms_slope",
    "THRESHOLD_UNIT",
    "threshold_attrs",
]

TRIGGER_SOURCES = ("software", "genicam", "line0", "line1", "line2", "line3", "auto")

#: The unit of the auto-trigger's threshold as the window shows it, the settings remember it and every
#: recording file states it (``auto_trigger_threshold``), and of the RMS slope its trigger event stores
#: (``rms_mrad``).
THRESHOLD_UNIT = "mrad RMS slope"


def threshold_attrs(threshold_mrad: Optional[float]) -> dict:
    """What a recording file stores about its auto-trigger (the unit with the value); {} for none."""
    if threshold_mrad is None:
        return {}
    return {"auto_trigger_threshold": float(threshold_mrad), "auto_trigger_threshold_unit": THRESHOLD_UNIT,
            "auto_trigger_quantity": "sqrt(mean(slope_x^2 + slope_y^2)) over the live slope maps"}


class TriggerError(RuntimeError):
    """A trigger could not be configured or a capture could not be armed; the message says why."""


def frames_for_seconds(seconds: float, frame_rate_hz: Optional[float], what: str = "duration") -> int:
    """Frames that cover ``seconds`` at ``frame_rate_hz`` (rounded up); errors name what is missing."""
    if seconds < 0:
        raise ValueError(f"{what} must be >= 0 seconds; got {seconds!r}")
    if not frame_rate_hz:
        raise TriggerError(
            f"cannot convert {what}={seconds:g} s to frames: the camera reports no frame rate; give frames instead"
        )
    return int(math.ceil(float(seconds) * float(frame_rate_hz) - 1e-9))


def configure_trigger(camera, source: str, *, activation: str = "RisingEdge") -> CameraSettings:
    """Write the camera's trigger settings for ``source`` and check what it accepted.

    ``software`` and ``auto`` set ``trigger_mode="Off"`` (free running);
    ``genicam`` sets On/Software; ``lineN`` sets On/LineN/``activation``.
    Raises :class:`TriggerError` when the camera refuses or reads back something else.
    """
    source = source.lower()
    if source not in TRIGGER_SOURCES:
        raise TriggerError(f"unknown trigger source {source!r}; use one of {', '.join(TRIGGER_SOURCES)}")
    if source in ("software", "auto"):
        want = dict(trigger_mode="Off")
    elif source == "genicam":
        want = dict(trigger_mode="On", trigger_source="Software")
    else:
        want = dict(trigger_mode="On", trigger_source="Line" + source[4:], trigger_activation=activation)
    current = camera.settings()
    if all(getattr(current, k) == v for k, v in want.items()):
        return current  # nothing to change (and cameras without trigger features stay usable free running)
    try:
        got = camera.configure(**want)
    except SettingError as exc:
        raise TriggerError(f"camera {camera.camera_id!r} refused trigger source {source!r}: {exc}") from exc
    for k, v in want.items():
        if getattr(got, k) != v:
            raise TriggerError(
                f"camera {camera.camera_id!r} accepted {k}={getattr(got, k)!r} instead of {v!r} for trigger "
                f"source {source!r}; check the camera's trigger features"
            )
    return got


def rms_slope(slope_x: np.ndarray, slope_y: np.ndarray, region: Optional[Tuple[int, int, int, int]] = None) -> float:
    """RMS slope magnitude ``sqrt(mean(slope_x**2 + slope_y**2))`` (dimensionless) over ``region``; NaN if none valid.

    What :class:`AutoTrigger` compares with its threshold (the GUI shows it live, in mrad).
    """
    if slope_x.shape != slope_y.shape:
        raise ValueError(f"slope_x and slope_y must have equal shapes; got {slope_x.shape} and {slope_y.shape}")
    if region is not None:
        r0, r1, c0, c1 = region
        if r1 > slope_x.shape[0] or c1 > slope_x.shape[1]:
            raise ValueError(
                f"auto-trigger region {region} lies outside the {slope_x.shape} slope map; "
                "give a region inside it (the decimated grid is smaller than the frame)"
            )
        slope_x = slope_x[r0:r1, c0:c1]
        slope_y = slope_y[r0:r1, c0:c1]
    m = np.asarray(slope_x, np.float64) ** 2 + np.asarray(slope_y, np.float64) ** 2
    m = m[np.isfinite(m)]
    return float(np.sqrt(m.mean())) if m.size else float("nan")


class AutoTrigger:
    """Fires when the RMS slope in a region of the live slope maps exceeds a threshold.

    Parameters
    ----------
    threshold : float
        RMS of the slope magnitude, ``sqrt(mean(slope_x**2 + slope_y**2))``
        (dimensionless, i.e. mm/mm), above which it fires.
    region : (row0, row1, col0, col1) or None
        Half-open pixel box of the slope maps to watch; None: the whole map.
    dead_time_s : float
        After firing, ignore the signal for this many seconds.
    rearm : bool
        True: arm again by itself after the dead time. False: stay disarmed
        until :meth:`rearm` (one shot).
    callback : callable, optional
        ``callback(sequence, rms)`` when it fires (from the feeding thread).
    ready : callable, optional
        ``ready(sequence) -> bool``: whether a trigger on that frame can be
        taken now (e.g. :meth:`TriggeredCapture.ready_for`: its pre-trigger
        frames are in the ring). A crossing on a frame that is not ready is
        ignored and counted in ``not_ready``; the trigger stays armed.

    Publishes ``armed``, ``last_rms``, ``fired`` (count), ``last_fired_sequence``, ``not_ready``.
    NaN slopes (masked pixels) are ignored; a region with no valid slope never fires.
    """

    def __init__(self, threshold: float, region: Optional[Tuple[int, int, int, int]] = None, *,
                 dead_time_s: float = 1.0, rearm: bool = False,
                 callback: Optional[Callable[[int, float], None]] = None,
                 ready: Optional[Callable[[int], bool]] = None):
        if not threshold > 0:
            raise ValueError(f"auto-trigger threshold must be a positive RMS slope; got {threshold!r}")
        if dead_time_s < 0:
            raise ValueError(f"dead_time_s must be >= 0 s; got {dead_time_s!r}")
        if region is not None:
            region = tuple(int(v) for v in region)
            if len(region) != 4 or region[1] <= region[0] or region[3] <= region[2] or min(region) < 0:
                raise ValueError(f"region must be (row0, row1, col0, col1) with row0 < row1, col0 < col1; got {region}")
        self.threshold = float(threshold)
        self.region = region
        self.dead_time_s = float(dead_time_s)
        self.auto_rearm = bool(rearm)
        self.callback = callback
        self.ready = ready
        self.not_ready = 0
        self.armed = True
        self.last_rms = float("nan")
        self.fired = 0
        self.last_fired_sequence: Optional[int] = None
        self._last_fire_t: Optional[float] = None
        self._lock = threading.Lock()

    def rms(self, slope_x: np.ndarray, slope_y: np.ndarray) -> float:
        """RMS slope magnitude in the region (NaN when no valid pixel): :func:`rms_slope`."""
        return rms_slope(slope_x, slope_y, self.region)

    def feed(self, slope_x: np.ndarray, slope_y: np.ndarray, *, sequence: int, time_s: Optional[float] = None) -> bool:
        """Feed one slope map pair computed from ring frame ``sequence``; True when this fired."""
        t = time.monotonic() if time_s is None else float(time_s)
        value = self.rms(slope_x, slope_y)
        with self._lock:
            self.last_rms = value
            if not self.armed:
                if self.auto_rearm and self._last_fire_t is not None and t - self._last_fire_t >= self.dead_time_s:
                    self.armed = True
                else:
                    return False
            if self._last_fire_t is not None and t - self._last_fire_t < self.dead_time_s:
                return False
            if not (value > self.threshold):
                return False
            if self.ready is not None and not self.ready(int(sequence)):
                self.not_ready += 1
                return False
            self.armed = False
            self._last_fire_t = t
            self.fired += 1
            self.last_fired_sequence = int(sequence)
        if self.callback is not None:
            self.callback(int(sequence), value)
        return True

    def rearm(self) -> None:
        """Arm again now (the dead time still applies)."""
        with self._lock:
            self.armed = True


class TriggeredCapture:
    """Pre/post-trigger recording from an :class:`~app.capture.acquisition.Acquisition` into an HDF5 file.

    Parameters
    ----------
    acquisition : Acquisition
        The running (or about to run) camera thread; its ring holds the pre-trigger frames.
    path : str or Path
        Output file (never overwritten).
    pre_frames, post_frames : int
        Frames before the trigger frame, and from the trigger frame on.
    pre_s, post_s : float, optional
        The same in seconds (converted with the camera's frame rate, rounded up);
        give frames or seconds for each.
    source : str
        One of ``TRIGGER_SOURCES``; stored in the file.
    burst : bool or None
        True: write only after the capture is complete (burst to RAM; the ring
        must hold pre + post frames). None: decide -- burst when pre + post fit
        into the ring. False: write while capturing (long post-trigger runs).
    stop_camera : bool
        Stop the acquisition after the last post-trigger frame (no frame can
        then be overwritten before it is written).
    progress : callable, optional
        ``progress(frames_written, frames_planned)``.
    **file_options
        Passed to :class:`~app.capture.recorder.RecordingFile` (geometry_toml,
        reference_image, check_space, on_exists, attrs).

    Publishes ``state`` ("armed", "triggered", "done", "error", "cancelled"), ``trigger_sequence``, ``fired_by``,
    ``pre_frames``, ``post_frames``, ``recorder``, :meth:`summary`.
    Takes :meth:`trigger_now`, :meth:`trigger_at`, :meth:`wait`, :meth:`cancel`.
    """

    def __init__(self, acquisition, path, *, pre_frames: Optional[int] = None, post_frames: Optional[int] = None,
                 pre_s: Optional[float] = None, post_s: Optional[float] = None, source: str = "software",
                 burst: Optional[bool] = None, stop_camera: bool = True,
                 progress: Optional[Callable[[int, Optional[int]], None]] = None, **file_options):
        rate = acquisition.settings.frame_rate_hz
        if pre_frames is not None and pre_s is not None:
            raise ValueError(f"give pre_frames or pre_s, not both; got {pre_frames} and {pre_s}")
        if post_frames is not None and post_s is not None:
            raise ValueError(f"give post_frames or post_s, not both; got {post_frames} and {post_s}")
        pre = int(pre_frames) if pre_frames is not None else (
            frames_for_seconds(pre_s, rate, "pre_s") if pre_s is not None else 0)
        if post_frames is not None:
            post = int(post_frames)
        elif post_s is not None:
            post = frames_for_seconds(post_s, rate, "post_s")
        else:
            raise ValueError("give post_frames or post_s: how many frames from the trigger on to record")
        if pre < 0 or post < 1:
            raise ValueError(f"need pre >= 0 and post >= 1 frames; got pre={pre}, post={post}")
        source = source.lower()
        if source not in TRIGGER_SOURCES:
            raise TriggerError(f"unknown trigger source {source!r}; use one of {', '.join(TRIGGER_SOURCES)}")
        if source.startswith("line") and pre > 0:
            raise TriggerError(
                f"a hardware-line trigger makes the frames themselves, so there are no frames before it; "
                f"got pre={pre}: use pre 0 (or trigger source 'software'/'auto' with a free-running camera)"
            )
        ring = acquisition.ring
        if pre + 1 > ring.n_frames:
            raise TriggerError(
                f"{pre} pre-trigger frames do not fit into the ring of {ring.n_frames} frames; "
                "enlarge the ring or use fewer pre-trigger frames"
            )
        if burst is None:
            burst = pre + post <= ring.n_frames
        elif burst and pre + post > ring.n_frames:
            raise TriggerError(
                f"burst of {pre} + {post} frames does not fit into the ring of {ring.n_frames} frames "
                f"({ring.nbytes / 1e9:.2f} GB); enlarge the ring or capture without burst"
            )
        self.acquisition = acquisition
        self.pre_frames = pre
        self.post_frames = post
        self.source = source
        self.burst = bool(burst)
        self.stop_camera = bool(stop_camera)
        attrs = dict(file_options.pop("attrs", None) or {})
        attrs.update(trigger_source=source, pre_frames=pre, post_frames=post,
                     frame_rate_hz=rate if rate else -1.0, burst=int(self.burst))
        self.recorder = Recorder(ring, path, n_frames=pre + post, acquisition=acquisition, defer=self.burst,
                                 progress=progress, attrs=attrs, **file_options)
        self.path = self.recorder.path
        self.state = "armed"
        self.trigger_sequence: Optional[int] = None
        self.fired_by: Optional[str] = None  # the source that fired it (trigger_now, the auto-trigger)
        self.pre_available: Optional[int] = None
        self._armed_head = ring.head
        self._lock = threading.Lock()
        if source.startswith("line"):
            # the line makes the frames: the first frame after arming is the trigger frame
            self.trigger_at(self._armed_head)

    # ------------------------------------------------------------ trigger
    def trigger_now(self, source: Optional[str] = None) -> int:
        """Trigger on the newest frame in the ring (the next one if none came yet); returns its sequence.

        ``source``: what fired it, stored in the file (default: the capture's own source; the GUI's button
        or key press passes "software", even when an auto-trigger was armed beside it).
        """
        ring = self.acquisition.ring
        return self.trigger_at(max(ring.head - 1, 0), host_timestamp_ns=time.monotonic_ns(), source=source)

    def trigger_at(self, sequence: int, *, host_timestamp_ns: Optional[int] = None, source: Optional[str] = None,
                   **info) -> int:
        """Make ring frame ``sequence`` the trigger frame (auto-trigger: the frame the slopes came from).

        ``source``: what fired it (one of ``TRIGGER_SOURCES``; default the capture's own), stored as the
        file's ``trigger_source``.
        """
        source = self.source if source is None else source.lower()
        if source not in TRIGGER_SOURCES:
            raise TriggerError(f"unknown trigger source {source!r}; use one of {', '.join(TRIGGER_SOURCES)}")
        with self._lock:
            if self.state != "armed":
                return self.trigger_sequence if self.trigger_sequence is not None else -1
            ring = self.acquisition.ring
            seq = int(sequence)
            self.trigger_sequence = seq
            self.fired_by = source
            self.state = "triggered"
            ring.add_flags(seq, FrameFlags.TRIGGER)
            rec = self.recorder
            if self.stop_camera:
                self.acquisition.stop_after(seq + self.post_frames - 1)
            try:  # nothing slow (the file) before the recorder holds its first frame: the camera goes on
                start = self._begin_recorder(seq, source)
            except RecorderError:
                self.state = "error"
                raise
            self.pre_available = seq - start
            rec.set_trigger(seq, host_trigger_ns=int(host_timestamp_ns or time.monotonic_ns()),
                            source=source, pre_available=self.pre_available, **info)
            if self.pre_available < self.pre_frames:
                rec.file.add_event("note", f"only {self.pre_available} of {self.pre_frames} pre-trigger frames "
                                           "existed when the trigger came", sequence=seq)
            return seq

    def _begin_recorder(self, seq: int, source: str) -> int:
        """Start the recorder at the first pre-trigger frame the ring still holds; returns that sequence.

        The camera goes on writing meanwhile: after a stall it delivers a burst of frames, and one that
        overwrites the start between reading ``ring.oldest`` and the recorder's cursor made the whole
        recording fail (``RecorderError``: seen once in a test run, a 48-frame ring at 500 Hz lapped by
        65 frames while the trigger wrote the file's attributes; the recorder writes them now, once its
        cursor holds the start). The start then moves up to what is left, as for a trigger that came
        before the pre-trigger frames existed: fewer pre-trigger frames, said in a note. Only a trigger
        frame that is itself overwritten is an error.
        """
        ring, rec = self.acquisition.ring, self.recorder
        while True:
            start = max(seq - self.pre_frames, ring.oldest, 0)
            rec.n_frames = (seq - start) + self.post_frames
            try:
                rec.begin(start, trigger_sequence=seq, attrs={"trigger_source": source})
                return start
            except RecorderError:
                if seq < ring.oldest or start >= ring.oldest:  # the trigger frame is gone, or another error
                    raise

    def ready_for(self, sequence: int) -> bool:
        """True when a trigger on ring frame ``sequence`` would get all ``pre_frames`` before it.

        An auto-trigger passes this as its ``ready`` gate, so that a signal
        already above threshold at arming cannot make a file with fewer
        pre-trigger frames than asked for.
        """
        ring = self.acquisition.ring
        return int(sequence) - self.pre_frames >= max(ring.oldest, 0)

    def auto_callback(self) -> Callable[[int, float], None]:
        """A callback for :class:`AutoTrigger` that triggers this capture on the frame that crossed."""

        def fire(sequence: int, rms: float) -> None:
            # the event holds the RMS slope as compared (mm/mm) and in the threshold's unit: a file that
            # said rms 5.47e-05 beside a threshold of 0.001 "mrad RMS slope" read as fired at 1/20 of it
            self.trigger_at(sequence, rms=rms, rms_mrad=1e3 * float(rms), source="auto")

        return fire

    # --------------------------------------------------------------- wait
    def wait(self, timeout_s: float) -> bool:
        """Wait for the recording to end (after a trigger); True if it ended within ``timeout_s``."""
        if self.trigger_sequence is None:
            return False
        ok = self.recorder.wait(timeout_s)
        if ok:
            self.state = "error" if self.recorder.error else "done"
        return ok

    @property
    def error(self) -> Optional[str]:
        return self.recorder.error

    def cancel(self, timeout_s: float = 10.0, why: str = "stopped by the user") -> bool:
        """Give up: before the trigger the file (no frame in it) is deleted; after it, every frame already in the
        ring is written (they were captured: a disarm just after the trigger kept 1 of them, by-hand trial of
        7 Dec 2026) and the file closed, ``why`` in its ``/events`` (it read "ok" alone).

        Returns True when a file was kept.
        """
        with self._lock:
            if self.state == "armed":
                self.state = "cancelled"
                self.recorder.discard()
                return False
        ring = self.acquisition.ring
        self.recorder.file.add_event("note", f"{why}: the recording ends at the frames captured until then",
                                     sequence=ring.head)
        self.recorder.stop(timeout_s, drain=True)
        return True

    def summary(self) -> dict:
        s = self.recorder.summary()
        if self.pre_available is not None and self.pre_available < self.pre_frames:
            # the recorder plans what existed; what was asked for is pre + post (the file's `complete` says so too)
            s["frames_planned"] = self.pre_frames + self.post_frames
        s.update(pre_frames=self.pre_frames, post_frames=self.post_frames,
                 pre_available=-1 if self.pre_available is None else self.pre_available,
                 trigger_source=self.fired_by or self.source, burst=self.burst)
        return s
