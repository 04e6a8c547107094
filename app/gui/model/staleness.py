"""How old is what the window shows, and why it is not the camera's present.

Every view records what it shows as a :class:`Shown` (frame number, driver host
timestamp, the acquisition it came from). :func:`view_staleness` turns those and
the clock into the text each view is marked with (None: live). Numbers derived
from the processed maps (the status bar's "vs truth", probes) carry the maps'
mark through :func:`derived_text`, so they are greyed exactly when the maps are.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

__all__ = ["STALE_AFTER_S", "NO_REFERENCE", "NOT_DRAWN", "Shown", "Staleness", "ReferenceEpochs", "format_age",
           "why_stale", "view_staleness", "derived_text", "short_derived_text", "unmeasured_messages"]

#: A view whose data is this much older than expected is marked stale (s).
STALE_AFTER_S = 1.0
#: Why maps are stale whose reference (and geometry) the worker no longer measures with, none replacing it
#: (a refused reference, an ROI the reference does not cover).
NO_REFERENCE = "their reference is no longer in use"
#: Why the live maps are stale while another tab is shown (they are drawn on the Live tab only): the numbers
#: derived from them (the status bar's "vs truth", the auto-trigger readout, a snapshot) are as old.
NOT_DRAWN = "not redrawn while the Live tab is hidden"


def format_age(frame_id, age_s: float) -> str:
    """``"frame 1234, 2.3 s ago"`` (the words the stale marks use)."""
    age = f"{age_s:.1f} s" if age_s < 100 else f"{age_s / 60:.0f} min"
    return f"frame {frame_id}, {age} ago" if frame_id is not None else f"{age} ago"


@dataclasses.dataclass(frozen=True)
class Shown:
    """What a view shows.

    seq : worker frame number (None: unknown); host_ns : driver host timestamp (ns, monotonic clock;
    0: unknown); source : a callable returning the acquisition the frame came from, or None once it
    is gone (a weak reference), or None; camera_key : the camera id and ROI it was measured with;
    reference_key : the reference (and geometry) the maps were computed against.
    """

    seq: Optional[int]
    host_ns: int
    source: Optional[Callable[[], Any]] = None
    camera_key: Any = None
    reference_key: Any = None

    def age_s(self, now_ns: int) -> float:
        return (now_ns - self.host_ns) / 1e9 if self.host_ns else 0.0


def why_stale(shown: Optional[Shown], acquisition, camera_key: Any = None) -> Optional[str]:
    """Why data from ``shown`` is not the camera's present (None: it is).

    ``camera_key``: ``(camera identity, region of interest)`` of the open camera. The same camera
    restarted with another ROI (a new acquisition) says "ROI changed", with other settings "camera settings
    changed", not "from the previous camera".
    """
    if shown is None:
        return None
    source = shown.source() if shown.source is not None else None
    if source is None or source is not acquisition:
        if acquisition is None:
            return "camera closed"
        if camera_key is not None and shown.camera_key is not None and shown.camera_key[0] == camera_key[0]:
            return "camera settings changed" if shown.camera_key == camera_key else "ROI changed"
        return "from the previous camera"
    if getattr(acquisition, "error", None):
        return "camera lost"
    return None


@dataclasses.dataclass
class ReferenceEpochs:
    """The reconstructor rebuild policy, and which reference each processed frame was measured against.

    Every change of reference, geometry or device asks for a new reconstructor, built in the background
    (:meth:`request` gives the request's number). When a build ends, :meth:`outcome` says what to do with
    it: only the newest request may change what the worker uses ("install" or, when it failed, "remove":
    the worker then measures nothing), an older one is "superseded" and dropped, also when it failed (it
    must not take away a newer reference). :meth:`key` is the reference in use, the ``reference_key`` of
    :func:`view_staleness`: the newest request while the worker has a reconstructor, None when it has
    none; maps measured against anything else are stale.
    """

    requested: int = 0  # requests made
    installed: Optional[int] = None  # the request whose reconstructor the worker measures with (None: none)
    previous: Optional[int] = None  # the one before it: frames up to ``since_seq`` were measured with that
    since_seq: int = -1

    def request(self) -> int:
        self.requested += 1
        return self.requested

    def outcome(self, request: int, built: bool) -> str:
        """``"install"``, ``"remove"`` (the newest request failed) or ``"superseded"``."""
        if request != self.requested:
            return "superseded"
        return "install" if built else "remove"

    def install(self, request: int, since_seq: Optional[int]) -> None:
        """The worker measures frames after ``since_seq`` with the reconstructor of ``request``."""
        if self.installed is not None:  # after a removal the one before it measured the frames in flight
            self.previous = self.installed
        self.installed = int(request)
        self.since_seq = -1 if since_seq is None else int(since_seq)

    def remove(self, since_seq: Optional[int] = None) -> None:
        """The worker has no reconstructor any more (frames after ``since_seq`` are not measured)."""
        if self.installed is not None:
            self.previous = self.installed
        self.installed = None
        self.since_seq = self.since_seq if since_seq is None else int(since_seq)

    def measured_with(self, seq: Optional[int]) -> Optional[int]:
        """The request whose reconstructor measured frame ``seq`` (None: unknown frame: the newest).

        Frames after ``since_seq`` were measured with the one installed, those up to it with the one
        before; where that one is None, the result can only come from the other: a result has a
        reconstructor, and the worker (another process, late under load) may measure a frame it took
        before it learned of an install or a removal. Labelled None ("no reference to compare with"),
        such maps were never stale for their reference: after the first reference, the first maps could
        carry None and stay live-looking after a refused reference (seen once in a run loaded to twice
        the cores: not stale after 60 s)."""
        if seq is None or seq > self.since_seq:
            first, second = self.installed, self.previous
        else:
            first, second = self.previous, self.installed
        return first if first is not None else second

    def key(self, worker_has_reconstructor: bool = True):
        """The reference in use (:func:`view_staleness`'s ``reference_key``): None when the worker has none
        (removed by a failed build, or by anyone else: ``worker_has_reconstructor``)."""
        return self.requested if self.installed is not None and worker_has_reconstructor else None


@dataclasses.dataclass(frozen=True)
class Staleness:
    """The marks of one moment: None where the view is live, else ``"why — frame n, t s ago"``."""

    raw: Optional[str] = None
    maps: Optional[str] = None
    alignment: Optional[str] = None


def _mark(why: Optional[str], shown: Shown, now_ns: int) -> Optional[str]:
    return f"{why} — {format_age(shown.seq, shown.age_s(now_ns))}" if why else None


def view_staleness(now_ns: int, acquisition, *, raw: Optional[Shown], maps: Optional[Shown],
                   alignment: Optional[Shown], unmeasured_seq: Optional[int] = None,
                   frame_rate_hz: Optional[float] = None, camera_key: Any = None,
                   reference_key: Any = None, maps_drawn: bool = True,
                   newest_seq: Optional[int] = None) -> Staleness:
    """The stale marks of the raw views, the processed maps and the alignment views.

    Parameters
    ----------
    now_ns : int
        ``time.monotonic_ns()`` now (the clock of the drivers' host timestamps).
    acquisition
        The running acquisition (or None).
    raw, maps, alignment : Shown or None
        What those views show.
    unmeasured_seq : int, optional
        A newer frame the worker could not measure (no reference, an error): the maps are older.
    frame_rate_hz : float, optional
        The camera's rate: the raw view is stale after 3 frame periods without a new frame (>= 1 s).
    camera_key
        The open camera's (id, ROI), see :func:`why_stale`.
    reference_key
        The reference in use (:meth:`ReferenceEpochs.key`; None: none, the worker measures nothing): maps
        computed against another one are stale at once, whatever the worker and the raw view do next:
        "older reference" while a newer one is built or after it came, :data:`NO_REFERENCE` when none
        replaced theirs (a refused reference).
    maps_drawn : bool
        Whether the window draws the live maps now (False: another tab is shown). Maps not drawn for longer
        than the raw view's bound while the camera gave newer frames (``newest_seq``, its newest frame's
        number) are stale: :data:`NOT_DRAWN`.
    newest_seq : int, optional
        The number of the camera's newest frame (None: unknown).
    """
    raw_text = maps_text = align_text = None
    if raw is not None:
        why = why_stale(raw, acquisition, camera_key)
        if why is None and raw.age_s(now_ns) > max(STALE_AFTER_S, 3.0 / (frame_rate_hz or 10.0)):
            why = "no newer frame"
        raw_text = _mark(why, raw, now_ns)
    if maps is not None:
        why = why_stale(maps, acquisition, camera_key)
        if why is None and maps.reference_key is not None and maps.reference_key != reference_key:
            why = "older reference" if reference_key is not None else NO_REFERENCE
        elif why is None and not maps_drawn and newest_seq is not None and maps.seq is not None \
                and newest_seq > maps.seq and maps.age_s(now_ns) > max(STALE_AFTER_S, 3.0 / (frame_rate_hz or 10.0)):
            why = NOT_DRAWN
        elif why is None and unmeasured_seq is not None and maps.seq is not None and unmeasured_seq > maps.seq:
            why = f"newer frame {unmeasured_seq} not measured"
        elif why is None and raw is not None and raw.seq is not None and maps.seq is not None \
                and raw.seq > maps.seq and raw.host_ns - maps.host_ns > STALE_AFTER_S * 1e9:
            why = "processing behind the camera"
        maps_text = _mark(why, maps, now_ns)
    if alignment is not None:
        why = why_stale(alignment, acquisition, camera_key)
        if why is None and raw is not None and raw.host_ns - alignment.host_ns > 2 * STALE_AFTER_S * 1e9:
            why = "not refreshed"
        align_text = _mark(why, alignment, now_ns)
    return Staleness(raw_text, maps_text, align_text)


def derived_text(text: str, maps_mark: Optional[str], *, measured_seq: Optional[int] = None,
                 maps_seq: Optional[int] = None) -> tuple:
    """A number derived from the processed maps, with their age: ``(text, stale)``.

    ``maps_mark``: the maps' stale mark (:func:`view_staleness`). ``measured_seq``/``maps_seq``: the frame
    the number was computed from and the frame the maps on screen show; a number from another frame than
    the maps on screen (e.g. computed before a new reference) is stale too. A stale number keeps its
    value, says ``"(stale: why — frame n, t s ago)"`` and is drawn grey.
    """
    if maps_mark is None and measured_seq is not None and maps_seq is not None and measured_seq != maps_seq:
        maps_mark = f"from frame {measured_seq}, the maps show {maps_seq}"
    if maps_mark is None:
        return text, False
    return f"{text} (stale: {maps_mark})", True


def short_derived_text(text: str, maps_mark: Optional[str]) -> str:
    """The few words of :func:`derived_text` a narrow place can show: ``text`` and, when stale, its age
    (``"vs truth 1.2 % (waves) (STALE, 3.1 s ago)"``), the full mark going to a tooltip: a long reason
    would otherwise push the age out of sight, or the neighbours out of the status bar."""
    if maps_mark is None:
        return text
    age = maps_mark.rsplit(" — ", 1)[-1].rsplit(", ", 1)[-1]
    return f"{text} (STALE, {age})" if age.endswith(" ago") else f"{text} (STALE)"


def unmeasured_messages(error: Optional[str], has_reconstructor: bool, refused: str = "") -> tuple:
    """What the maps say over a frame the worker could not measure: ``(full, short)`` -- the full text on the
    height map, a few words (or None) on the small maps. Without a reconstructor: "no reference yet", or,
    where the newest reference was refused (``refused``: why), that it is not usable and the first sentence
    of why (by-hand trial of 7 Dec 2026: a reference refused for its pixel_mm left "no reference yet:
    capture one" on the maps, and capturing again would be refused again)."""
    if error:
        text = error
    elif has_reconstructor:
        text = ""
    elif refused:
        text = ("the reference is NOT usable: " + refused.split(". ")[0].rstrip(".")
                + " (the banner says what to change)")
    else:
        text = "no reference yet: capture one (Controls ▸ Reference & geometry)"
    short = "reference NOT usable (see Height)" if (refused and not error and not has_reconstructor) else None
    return text, short or (text.split(":")[0] + " (see Height)" if ":" in text else None)
