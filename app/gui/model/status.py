"""What the status bar says: the camera (LOST in red after a loss), the rates, drops per stage, the
ring buffer, the latency and where the live maps are computed, from the session's status."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

__all__ = ["StatusTexts", "status_texts", "drops_text", "ring_texts", "truth_texts", "camera_problem"]


@dataclasses.dataclass(frozen=True)
class StatusTexts:
    """One refresh of the status bar (``*_tip``: tooltips; ``camera_lost``: drawn red and bold)."""

    camera: str
    camera_lost: bool
    camera_fps: float
    fps: str
    drops: str  # a few words that fit a laptop's status bar: the losses (red when any), the backlog
    drops_tip: str  # every counter, the display's skips included
    drops_alarm: bool  # a frame was lost (camera or ring -> recorder): drawn red and bold
    ring: str
    ring_tip: str
    latency: str
    device: str
    device_tip: str
    device_failed: bool  # the reconstruction process died: shown red
    state: str


def status_texts(st: dict, *, camera_fps: float, processed_fps: float, shown_fps: float, frozen: bool,
                 camera_open: bool, display_skipped: int, latency_ms: float, device_text: str = "",
                 reconstructed_in: str = "", process_error: str = "",
                 last_on_gpu: Optional[bool] = None, process_starting: Optional[tuple] = None) -> StatusTexts:
    """The texts from ``st`` (``LiveSession.status()``) and the rates measured by the window.

    ``camera_fps``/``processed_fps``: :class:`~app.gui.model.schedule.LiveRates` (0 once nothing new came);
    a lost or closed camera gives 0 whatever its last rate; ``frozen``: Pause or a script holds the views
    (nothing new is shown: 0); ``device_text``: the live Reconstructor's ``device_text``;
    ``reconstructed_in``: where the worker runs it (its process or the window's);
    ``process_error``: why the reconstruction process died ("" while it lives): heights go on in the
    window's process, slower, and the label says so in red; ``last_on_gpu``: where the newest live
    result was computed (:func:`processing.gpu.ran_on_gpu`; None before the first): a GPU
    reconstructor hands each frame it cannot do to the CPU, and the label says so rather than "GPU";
    ``process_starting``: ``(seconds, timeout_s)`` while the reconstruction process has not answered yet
    (:attr:`app.capture.worker.ProcessingWorker.process_starting`): the label says it is starting, and for
    how long (a process that never answered read "live on CPU", processed 0 fps, no maps and no word for
    the three minutes of its start timeout: by-hand trial, 7 Dec 2026).
    """
    if last_on_gpu is False and device_text.startswith("GPU"):
        device_text = (f"CPU (asked for the {device_text}, which takes only frames valid everywhere: "
                       "this frame has masked samples, folds or 2 pi jumps since the last, or starts a series)")
    err = st.get("error")
    camera_fps = 0.0 if err or not camera_open else float(camera_fps)
    shown_fps = 0.0 if frozen else float(shown_fps)
    ring, ring_tip = ring_texts(st, camera_fps)
    return StatusTexts(
        camera=f"{st.get('camera_text', 'camera')} LOST" if err else st.get("camera_text", ""),
        camera_lost=bool(err), camera_fps=camera_fps,
        fps=f"camera {camera_fps:.1f} · processed {processed_fps:.1f} · shown {shown_fps:.1f} fps",
        drops=drops_text(st),
        drops_tip=(f"dropped: camera {st.get('dropped_camera', 0)} · ring→recorder {st.get('dropped_ring', 0)} · "
                   f"recorder backlog {st.get('recorder_backlog', 0)} · live heights skipped {display_skipped} "
                   f"(a newer frame was there; the recording keeps every frame)"
                   + (f" · incomplete {st['incomplete_camera']} (delivered with network packets missing: kept, "
                      "the missing pixels are 0)" if st.get("incomplete_camera") else "")),
        drops_alarm=bool(st.get("dropped_camera", 0) or st.get("dropped_ring", 0) or st.get("incomplete_camera", 0)),
        ring=ring, ring_tip=ring_tip,
        latency=f"latency {latency_ms:.0f} ms" if math.isfinite(latency_ms) else "",
        device=(f"live on {device_text.split(' (')[0]}"
                + (" in the window's process (the reconstruction process died)" if process_error else
                   f": its process starting ({process_starting[0]:.0f} s)" if process_starting else "")
                if device_text else ""),
        device_tip=(process_error or (
            f"the live reconstruction process has not answered yet ({process_starting[0]:.0f} s: its imports and "
            f"first build, a few seconds; after {process_starting[1]:.0f} s it is ended and the heights go on in "
            f"the window's process)" if process_starting else
            f"live reconstruction on the {device_text}" + (f", {reconstructed_in}" if reconstructed_in else "")))
            if device_text else "",
        device_failed=bool(process_error),
        state="camera stopped" if err else "")


def ring_texts(st: dict, camera_fps: float) -> tuple:
    """``(text, tip)`` of the ring buffer: the history it holds (seconds at the camera's rate, else frames:
    what a trigger can keep from before it) and, while a recording runs, how far behind the camera the
    recorder is (its share of the ring: at 100 % frames would be lost). "ring 100 %" (full) read as an
    alarm beside "dropped: none" in a by-hand trial, though a ring is full as soon as it has wrapped: the
    oldest frame makes room, nothing is lost."""
    held, n = st.get("ring_held"), int(st.get("ring_frames", 0) or 0)
    if held is None or n <= 0:
        return "", ""
    span = f"{held / camera_fps:.1f} s" if camera_fps > 0 else f"{held} frames"
    text, tip = f"ring {span}", (f"ring buffer: the last {held} of {n} frames" +
                                 (f" ({held / camera_fps:.1f} s at {camera_fps:.0f} fps)" if camera_fps > 0 else "") +
                                 " in memory, the most a trigger can keep from before it; once full, the oldest frame "
                                 "makes room for each new one: nothing is lost")
    backlog = int(st.get("recorder_backlog", 0) or 0)
    if backlog:
        share = 100.0 * backlog / n
        text += f" · recorder {share:.0f} % behind"
        tip += (f"; the recorder is {backlog} frames ({share:.0f} % of the ring) behind the camera: at 100 % "
                "it would lose frames (counted as ring→recorder)")
    return text, tip


def drops_text(st: dict) -> str:
    """The status bar's few words on lost frames: ``"dropped: none"`` while no frame was lost, else the
    losses per stage (``"DROPPED camera 2 · ring→recorder 0"``), and the recorder's backlog when it has
    one. The whole sentence, with the counters that are not losses, was cut to "dropped: ca…" at
    1280x800 (by-hand trial 2 Dec 2026): the one number a user must see was the first to go.

    Frames the camera delivered with pixels missing (GigE packets lost: kept, the missing pixels 0) are
    ``"INCOMPLETE n"``, not dropped: counted as "DROPPED camera", a lossy link's 212 damaged frames read as
    212 lost while the recording beside it said "lost upstream 0" (by-hand trial, fake GigE camera with
    ``-r 20``, 7 Dec 2026)."""
    camera, ring, incomplete = st.get("dropped_camera", 0), st.get("dropped_ring", 0), st.get("incomplete_camera", 0)
    text = f"DROPPED camera {camera} · ring→recorder {ring}" if camera or ring else "dropped: none"
    if incomplete:
        text = f"{text} · INCOMPLETE {incomplete}"
    backlog = st.get("recorder_backlog", 0)
    return f"{text} · backlog {backlog}" if backlog else text


def camera_problem(error: Optional[str], camera_id: Optional[str], already_shown: Optional[str]) -> Optional[str]:
    """The banner's text for a camera error not yet shown (None: no error, or this one is up already)."""
    if not error or error == already_shown:
        return None
    from app.gui.camera_messages import explain_open_error, is_controlled_elsewhere

    if is_controlled_elsewhere(error):  # another program holds the camera: say so, not "check the cable"
        return f"Camera problem: {explain_open_error(camera_id, error)}"
    return (f"Camera problem: {error}\nCheck the cable, power and network, then press Open in Controls ▸ Camera. "
            "The app keeps running; frames already recorded are kept.")


def truth_texts(error: dict) -> tuple:
    """``(text, brief)`` of the synthetic tank's "vs truth" (:func:`app.capture.scene.height_error`'s ``error``
    with its ``scene``): the relative RMS error where the truth moves enough to be measured against
    (``"vs truth 1.2 % rel. RMS (waves)"``, brief without "rel. RMS" for the status bar), else the error itself
    and the truth's RMS (``"vs truth 0.3 nm RMS of 3.4 nm (drop)"``; still water: no truth's)."""
    scene = error.get("scene", "")
    if math.isfinite(error.get("rel_rms", float("nan"))):
        pct = 100 * error["rel_rms"]
        return f"vs truth {pct:.1f} % rel. RMS ({scene})", f"vs truth {pct:.1f} % ({scene})"
    truth = error.get("rms_truth_mm", float("nan"))
    of = f" of {_small_height(truth)}" if truth >= 1e-9 else ""
    text = f"vs truth {_small_height(error.get('rms_error_mm', float('nan')))} RMS{of} ({scene})"
    return text, text


def _small_height(mm: float) -> str:
    """A small height: nm below 10 nm ("0.000 µm" said nothing), else µm."""
    return f"{1e6 * mm:.1f} nm" if mm < 1e-5 else f"{1e3 * mm:.3f} µm"
