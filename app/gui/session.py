"""The live pipeline behind the window, wired in one place (no widgets here).

::

    camera (drivers) -> Acquisition thread -> RingBuffer -> recorder (every frame, own cursor)
                                                         -> ProcessingWorker (newest only) -> window

Everything here may block (opening cameras, capturing a reference, arming a
recording); the window calls those methods from background threads. Status
getters never block.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
import weakref
from typing import Optional

import numpy as np

from app.capture.worker import ProcessingWorker

__all__ = ["LiveSession", "Opened", "NO_OVERLAP_WITH_DISCOVERY"]

#: Held while cameras are searched (Aravis discovery) and while a Reconstructor is
#: built in the background: a fresh-clone test run froze, every thread waiting, with
#: a build importing OpenPIV/scipy for the first time in one thread while
#: ``Aravis.update_device_list()`` ran in another (reproduced twice; why they
#: deadlock is not understood). The two never overlap now; each waits for the
#: other (discovery is bounded to a few seconds).
NO_OVERLAP_WITH_DISCOVERY = threading.Lock()


@dataclasses.dataclass
class Opened:
    """What :meth:`LiveSession.open` found and started."""

    camera_id: str
    settings: object
    cameras: list
    note: str = ""
    reference: Optional[np.ndarray] = None
    geometry: object = None
    use_scene_reference: bool = False
    restore: bool = True  # apply what the last session remembered for this camera (settings, reference)


class LiveSession:
    """Camera, acquisition, processing worker, trigger and recorder of the live window.

    Parameters
    ----------
    synthetic_options : dict, optional
        Keyword arguments for :class:`app.capture.scene.TankScene` (``shape``, ``n_frames``, ``bits``,
        ``noise_rms``) and ``frame_rate_hz`` of the synthetic camera.
    ring_bytes : int
        Memory for the camera ring buffer (bytes); the pre-trigger length must fit.
    stall_timeout_s : float
        A free-running camera that delivers nothing for this long is declared lost.
    worker_process : bool
        Reconstruct the live heights in a worker process of their own (its own GIL:
        ``app/capture/live_process.py``); False: in the worker thread of this process.
    """

    def __init__(self, *, synthetic_options: Optional[dict] = None, ring_bytes: int = 512 * 2**20,
                 stall_timeout_s: float = 3.0, worker_nice: int = 0, worker_process: bool = True):
        self.synthetic_options = dict(synthetic_options or {})
        self.ring_bytes = int(ring_bytes)
        self.stall_timeout_s = float(stall_timeout_s)
        self.camera = None
        self.acquisition = None
        self.camera_id: Optional[str] = None
        self.reference: Optional[np.ndarray] = None
        self._lock = threading.RLock()
        self._settings = None
        self._latest_out = None
        self._source_acq = None
        self._seq_base = 0
        # frame numbers run on across camera restarts: each acquisition's first frame is numbered after
        # every frame of the ones before (the raw view, the worker and the stale marks use one numbering)
        self._base_of = weakref.WeakKeyDictionary()
        self._frames_before = 0
        self._closed = False
        self.tank = None  # the synthetic camera's app.capture.scene.TankScene (scenes, true heights)
        self._frame_ids = {}  # worker seq -> camera frame id (recent frames; truth lookup)
        self._incomplete_pct = {}  # worker seq -> % of the frame's bytes lost on the network (incomplete ones)
        self.worker = ProcessingWorker(self._newest_frame, grid="decimated", nice=worker_nice,
                                       separate_process=worker_process)
        self.worker.start()
        self.capture = None  # app.capture.trigger capture (pre/post) while armed
        self.recording: Optional[dict] = None
        self._auto_trigger = None

    # ------------------------------------------------------------ cameras
    @staticmethod
    def list_cameras():
        """``(infos, note)`` from :func:`drivers.list_cameras` (synthetic always offered)."""
        import drivers

        with NO_OVERLAP_WITH_DISCOVERY:
            infos = list(drivers.list_cameras())
        real = [i for i in infos if i.backend != "synthetic"]
        note = (f"{len(real)} camera(s) found" if real else
                "no camera found: the synthetic camera (ray-traced water surface) stands in")
        return infos, note

    def open(self, camera_id: Optional[str] = None) -> Opened:
        """Open ``camera_id`` (None: first real camera, else synthetic) and start streaming.

        Cameras are searched only when ``camera_id`` is None (the search takes about a second);
        the synthetic camera is the simulated tank (:class:`app.capture.scene.TankScene`), on still
        water, streaming within a fraction of a second.
        """
        from app.capture.scene import TankScene

        opts = dict(self.synthetic_options)
        rate = float(opts.pop("frame_rate_hz", 60.0))
        opts.pop("scene", None)
        infos, note, pending = [], "", None
        if camera_id is None:
            # the search takes about a second: ray-trace the still tank meanwhile, in case none is found
            import concurrent.futures

            pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="tank")
            pending = pool.submit(TankScene, opts.get("shape", (512, 512)), frame_rate_hz=rate,
                                  **{k: v for k, v in opts.items() if k != "shape"})
            pool.shutdown(wait=False)
            infos, note = self.list_cameras()
            real = [i for i in infos if i.backend != "synthetic"]
            camera_id = real[0].camera_id if real else "synthetic"
        reference = geometry = None
        if camera_id == "synthetic":
            from drivers.synthetic import SyntheticCamera

            tank = (pending.result() if pending is not None else
                    TankScene(opts.pop("shape", (512, 512)), frame_rate_hz=rate, **opts))
            camera = SyntheticCamera(tank, frame_rate_hz=rate, bit_depth=tank.bits, camera_id="synthetic")
            reference, geometry = tank.reference, tank.geometry
        else:
            import drivers

            tank = None
            try:
                camera = drivers.open_camera(camera_id)
            except Exception as exc:  # noqa: BLE001 - explained for the user, original kept as cause
                from .camera_messages import explain_open_error

                raise RuntimeError(explain_open_error(camera_id, exc)) from exc
        try:
            opened = self.use_camera(camera, camera_id=camera_id)
        except Exception as exc:  # noqa: BLE001 - e.g. streaming refused: another program controls it
            from .camera_messages import explain_open_error

            self.close_camera()  # let go of it at once
            self.camera_id = None  # the status bar named it as open

            raise RuntimeError(explain_open_error(camera_id, exc)) from exc
        self.tank = tank
        opened.cameras, opened.note = infos, "; ".join(n for n in (opened.note, note) if n)
        opened.reference, opened.geometry = reference, geometry
        opened.use_scene_reference = False
        return opened

    def frame_id_of(self, seq: int) -> Optional[int]:
        """Camera frame id of the worker's frame ``seq`` (recent frames only), or None."""
        return self._frame_ids.get(int(seq))

    def incomplete_pct_of(self, seq: int) -> float:
        """Percentage of the worker's frame ``seq``'s bytes that the camera's link lost (stored as 0: an
        INCOMPLETE frame, :class:`drivers.base.FrameFlags`); 0.0 for a whole frame or one no longer known."""
        return self._incomplete_pct.get(int(seq), 0.0)

    def use_camera(self, camera, *, camera_id: Optional[str] = None) -> Opened:
        """Stream from an already constructed camera (opened here if needed); the old one is closed."""
        if self._closed:
            try:
                camera.close()
            finally:
                raise RuntimeError("the window is closing: camera not started")
        self.close_camera()
        self.tank = None
        if hasattr(camera, "open") and not getattr(camera, "_opened", False):
            camera.open()
        note = _to_mono(camera)
        with self._lock:
            self.camera = camera
            self.camera_id = camera_id or getattr(camera, "camera_id", "camera")
        self._restart_acquisition()
        return Opened(self.camera_id, self._settings, [], note)

    def _restart_acquisition(self):
        from app.capture.acquisition import Acquisition

        with self._lock:
            old = self.acquisition
            self.acquisition = None
        if old is not None:
            try:
                old.stop(timeout_s=5.0)
            except Exception:  # noqa: BLE001 - the old camera may be gone already
                pass
        settings = self.camera.settings()
        acq = Acquisition(self.camera, ring_bytes=self.ring_bytes, stall_timeout_s=self.stall_timeout_s)
        with self._lock:
            self._number_after(old)
            self._base_of[acq] = self._frames_before
        acq.start()
        with self._lock:
            self._settings = settings
            self.acquisition = acq
            self._latest_out = None
        self.worker.set_bit_depth(settings.bit_depth)

    def _number_after(self, acq) -> None:
        """Frames of ``acq`` (a stopped or replaced acquisition) count before the next one's (under the lock)."""
        if acq is not None and acq in self._base_of:
            self._frames_before = max(self._frames_before, self._base_of.pop(acq) + acq.ring.head)

    def camera_settings(self):
        return self._settings

    def configure(self, values: dict):
        """Write camera settings (acquisition restarted around it); returns the accepted settings."""
        if self.camera is None:
            raise RuntimeError("no camera is open: open one first (Controls ▸ Camera ▸ Open)")
        if self.capture is not None:
            raise RuntimeError("a recording is armed: disarm it before changing camera settings")
        with self._lock:
            acq, self.acquisition = self.acquisition, None
            self._number_after(acq)
        if acq is not None:
            acq.stop(timeout_s=5.0)
        try:
            accepted = self.camera.configure(**values)
        finally:
            self._restart_acquisition()
        return accepted

    def close_camera(self, why: str = "the camera was closed (another one chosen)"):
        self.disarm(why)
        with self._lock:
            acq, self.acquisition = self.acquisition, None
            cam, self.camera = self.camera, None
        if acq is not None:
            try:
                acq.stop(timeout_s=5.0)
            except Exception:  # noqa: BLE001
                pass
        with self._lock:
            # counted once stopped: a frame the camera committed while it stopped, handed to the worker
            # (which may still wait on this ring), must number below the next camera's first frame, or its
            # maps would pass for the next camera's (seen: "older reference" instead of "from the previous
            # camera" on a camera switch)
            self._number_after(acq)
        if cam is not None:
            try:
                cam.close()
            except Exception:  # noqa: BLE001
                pass

    # ------------------------------------------------------------- frames
    def _newest_frame(self, after_seq: int, timeout_s: float):
        """The worker's source: newest ring frame (copied), numbered on across camera restarts."""
        acq = self.acquisition
        if acq is None:
            time.sleep(min(timeout_s, 0.05))
            return None
        if acq is not self._source_acq:  # a new acquisition: its ring numbers from 0 again
            self._source_acq = acq
            self._seq_base = max(self._base_of.get(acq, after_seq + 1), after_seq + 1)
        f = acq.ring.latest(timeout_s)
        if f is None:
            if acq.ring.closed:
                time.sleep(min(timeout_s, 0.05))
            return None
        seq = self._seq_base + f.sequence
        ids = self._frame_ids
        ids[seq] = int(f.frame_id)
        if f.missing_bytes:
            self._incomplete_pct[seq] = 100.0 * f.missing_bytes / max(1, f.image.nbytes)
        for recent in (ids, self._incomplete_pct):
            if len(recent) > 512:
                for old in list(recent)[:256]:
                    recent.pop(old, None)
        return seq, f.image, f.host_timestamp_ns

    def sensor_origin_of(self, seq: int) -> Optional[tuple]:
        """``(row, col)`` on the sensor of pixel (0, 0) of frame ``seq`` (its ROI's offset, px); None when the
        frame came from an earlier acquisition (its ROI may have been another)."""
        with self._lock:  # the open acquisition and its settings are set together
            acq, settings = self.acquisition_of(seq), self._settings
        if acq is None or settings is None:
            return None
        return int(settings.offset_y), int(settings.offset_x)

    def acquisition_of(self, seq: Optional[int]):
        """The open acquisition if frame ``seq`` (numbered as ``Processed.seq``) is one of its frames, None
        if it came from an earlier one (a result still in flight when the camera changed)."""
        acq = self.acquisition
        if acq is None or seq is None:
            return acq
        return acq if seq >= self._base_of.get(acq, 0) else None

    def newest_seq(self) -> Optional[int]:
        """The number (as ``Processed.seq``) of the newest frame in the ring, None if none; copies nothing."""
        acq = self.acquisition
        if acq is None or acq.ring.head == 0:
            return None
        return self._base_of.get(acq, 0) + acq.ring.head - 1

    def latest_frame(self):
        """``(seq, image, host_ns)`` of the newest frame in the ring, copied; None if none. Never blocks.

        ``seq`` is numbered as the worker's ``Processed.seq`` (on across camera restarts).
        """
        acq = self.acquisition
        if acq is None:
            return None
        ring = acq.ring
        head = ring.head
        if head == 0:
            return None
        out = self._latest_out
        if out is None or out.shape != ring.shape or out.dtype != ring.dtype:
            out = self._latest_out = np.empty(ring.shape, ring.dtype)
        f = ring.copy(head - 1, out)
        if f is None:
            return None
        return self._base_of.get(acq, 0) + f.sequence, f.image, f.host_timestamp_ns

    def capture_reference(self, n_frames: int, timeout_s: Optional[float] = None, *,
                          pattern: str = "checkerboard"):
        """Average the next ``n_frames`` frames that agree with the first; blocks up to ``timeout_s``.

        Returns ``(reference float32 counts, ReferenceReport)``. Raises
        :class:`processing.reference_average.WaterMovingError` when the frames disagree (the water moves):
        :class:`~processing.reference_average.ReferenceAverager` says by how much.
        """
        from processing.reference_average import ReferenceAverager, WaterMovingError, first_frame_carriers

        acq = self.acquisition
        if acq is None:
            raise RuntimeError("no camera is streaming: open a camera first")
        if n_frames < 1:
            raise ValueError(f"average at least 1 frame; got {n_frames}")
        rate = (self._settings.frame_rate_hz or 10.0) if self._settings is not None else 10.0
        if timeout_s is None:
            timeout_s = 5.0 + 3.0 * n_frames / rate
        cursor = acq.ring.cursor()
        averager = None
        deadline = time.monotonic() + timeout_s
        while averager is None or len(averager.changes) < n_frames:
            got = 0 if averager is None else len(averager.changes)
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"only {got} of {n_frames} frames arrived within {timeout_s:.1f} s: "
                                   "is the camera delivering (trigger mode, frame rate)?")
            try:
                f = cursor.read(min(left, 0.5))
            except Exception as exc:  # RingClosed: camera lost
                raise RuntimeError(f"camera stopped while capturing the reference: {exc}") from None
            if f is None:
                continue
            if averager is None:
                averager = ReferenceAverager(first_frame_carriers(f.image, pattern))
            averager.add(f.image)
        try:
            return averager.result()
        except WaterMovingError:
            if averager.carriers_freq is None and pattern != "dots":  # frames of no checkerboard, changing
                from .model.reference import no_pattern_error

                raise WaterMovingError(no_pattern_error(averager.report().disagreement())) from None
            raise

    # ------------------------------------------------------------- status
    def status(self) -> dict:
        """Counters for the status bar (never blocks)."""
        acq = self.acquisition
        out = {"camera_text": "no camera" if self.camera_id is None else f"camera {self.camera_id}"}
        if acq is None:
            return out
        s = acq.stats()
        out["camera_fps"] = s["fps"]
        out["dropped_camera"] = s["lost_upstream"] + s["lost_by_time"]
        out["incomplete_camera"] = s["incomplete"]  # delivered with pixels missing (kept, stored as 0): not lost
        out["error"] = s["error"]
        rec = self.recording
        if rec is not None:
            out["dropped_ring"] = rec.get("ring_lost", 0)
            out["recorder_backlog"] = rec.get("backlog", 0)
        ring = acq.ring
        out["ring_held"] = min(ring.head, ring.n_frames)  # frames of history (all of them once it wrapped)
        out["ring_frames"] = ring.n_frames
        return out

    # ---------------------------------------------------------- recording
    def arm(self, folder: str, pre_frames: int, post_frames: int, *, reference=None, geometry_toml=None,
            auto_threshold: Optional[float] = None, name: Optional[str] = None) -> str:
        """Arm a pre/post-trigger capture into a new HDF5 file in ``folder``; returns its path.

        The camera keeps running (live view stays on); the recorder writes while
        capturing from its own ring cursor, so the display never slows it down.
        With ``auto_threshold`` (RMS slope, dimensionless; the file stores it in mrad with its unit), the processing worker's slope maps
        trigger it (:class:`app.capture.trigger.AutoTrigger`).
        """
        from app.capture.trigger import AutoTrigger, TriggeredCapture

        from .model.recording import mrad, threshold_attrs

        acq = self.acquisition
        if acq is None or not acq.running:
            raise RuntimeError("no camera is streaming: open a camera before arming")
        if self.capture is not None and self.recording and self.recording.get("state") in (
                "armed", "capturing", "saving"):
            raise RuntimeError("a recording is already armed or running: wait for it or disarm it")
        if not os.path.isdir(folder):
            raise OSError(f"recording folder {folder!r} does not exist: choose an existing folder")
        name = name or time.strftime("tirdeflect-%Y%m%d-%H%M%S.h5")
        path = os.path.join(folder, name)
        status = {"state": "armed", "progress": 0.0, "path": path, "error": None, "summary_text": "",
                  "pre": int(pre_frames), "post": int(post_frames)}

        def progress(done, total):
            status["written"] = int(done)
            if total:
                status["progress"] = float(done) / float(total)

        capture = TriggeredCapture(acq, path, pre_frames=int(pre_frames), post_frames=int(post_frames),
                                   source="auto" if auto_threshold else "software", burst=False,
                                   stop_camera=False, progress=progress, geometry_toml=geometry_toml,
                                   reference_image=None if reference is None else np.asarray(reference),
                                   on_exists="rename",
                                   attrs=threshold_attrs(mrad(auto_threshold) if auto_threshold else None))
        status["path"] = str(capture.path)
        self._capture_acq = acq
        self.capture = capture
        self.recording = status
        if auto_threshold:
            auto = AutoTrigger(float(auto_threshold), dead_time_s=0.0, callback=capture.auto_callback(),
                               ready=capture.ready_for)
            base = self._seq_base

            def feed(p, auto=auto, acq=acq, base=base):
                if p.result is None or self.acquisition is not acq or self.capture is not capture:
                    return
                auto.feed(p.result.slope_x, p.result.slope_y, sequence=p.seq - base)
                status["auto_rms"] = auto.last_rms

            self._auto_trigger = (auto, feed)
            self.worker.add_listener(feed)
        return status["path"]

    def trigger_now(self) -> int:
        """Trigger the armed capture on the newest frame (stored as "software": the user fired it)."""
        capture = self.capture
        if capture is None or capture.state != "armed":
            raise RuntimeError("nothing armed: press Arm first")
        return capture.trigger_now(source="software")

    def disarm(self, why: str = "disarmed in the window") -> str:
        """Cancel an armed capture: before its trigger no file is left; a running one keeps the frames captured
        (``why`` in its ``/events``).

        Returns what happened, for the panel.
        """
        capture, self.capture = self.capture, None
        self._drop_auto()
        text = "disarmed"
        if capture is not None:
            try:
                kept = capture.cancel(timeout_s=10.0, why=why)
            finally:
                if self.recording is not None:
                    self.recording.update(state="idle")
            text = (f"disarmed; {capture.path} kept with {capture.recorder.frames_written} frames" if kept else
                    "disarmed before the trigger: nothing recorded, no file written")
            if self.recording is not None:
                self.recording["summary_text"] = text
        return text

    def _drop_auto(self):
        auto, self._auto_trigger = self._auto_trigger, None
        if auto is not None:
            self.worker.remove_listener(auto[1])

    def recording_status(self) -> Optional[dict]:
        """``state`` (armed, capturing, saving, done, error), ``progress`` 0..1, ``path``, ``summary_text``..."""
        status, capture = self.recording, self.capture
        if status is None or capture is None:
            return status
        from app.capture.recorder import format_summary

        from .model.recording import armed_camera_lost_text

        lost = getattr(capture.acquisition, "error", None)
        if capture.state == "armed" and lost:  # nothing will ever trigger it: disarmed, and the panel says why
            self.disarm()
            status["summary_text"] = armed_camera_lost_text(lost)
            return status
        rec = capture.recorder
        status["ring_lost"] = rec.lost_overrun
        status["backlog"] = rec.backlog
        if capture.state == "armed":
            status["state"] = "armed"
        elif rec.done or capture.state in ("done", "error"):
            capture.wait(0.0)
            summary = capture.summary()
            status["summary"] = summary
            status["error"] = rec.error or None
            status["state"] = "error" if rec.error else "done"
            status["summary_text"] = format_summary(summary)
            status["progress"] = 1.0 if not rec.error else status["progress"]
            self.capture = None
            self._drop_auto()
        else:
            last = (capture.trigger_sequence or 0) + capture.post_frames - 1
            status["state"] = "saving" if capture.acquisition.ring.head > last else "capturing"
        return status

    # -------------------------------------------------------------- close
    def close(self):
        """Stop everything (idempotent); a camera opened later by a background job is refused."""
        self._closed = True
        self.close_camera("the window was closed")
        try:
            self.worker.stop(timeout_s=5.0)
        except TimeoutError:
            pass


def _to_mono(camera) -> str:
    """Set a camera left in a pixel format the app cannot measure (a colour or packed one, e.g. GenTL's
    "RGBa8") to the first mono format it accepts, Mono8 first; returns what the camera panel says of it
    ("" when it was mono).  The window refused such a camera with the driver's words for programmers
    ("configure(pixel_format=...)"), had let go of it, and Apply then said "no camera is open" (by-hand trial
    with the genicam wheel's GenTL camera, 7 Dec 2026): ``tirdeflect record`` names ``--pixel-format``."""
    from drivers.genicam_util import PIXEL_BITS

    try:
        before = camera.settings().pixel_format
    except Exception:  # noqa: BLE001 - a camera that cannot say: started as it is (its error says why)
        return ""
    if before in PIXEL_BITS:
        return ""
    for mono in PIXEL_BITS:
        try:
            camera.configure(pixel_format=mono)
        except Exception:  # noqa: BLE001 - not one this camera has: the next
            continue
        return (f"the camera was set to {before}, which cannot be measured (colour or packed): set to {mono} "
                "(Controls ▸ Camera ▸ Pixel format)")
    return ""
