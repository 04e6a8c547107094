"""What the window draws at each tick: raw frame, maps (in one tick or two halves), alignment, status bar and
stale marks (the rules are in app/gui/model/).

Functions take the :class:`app.gui.window.MainWindow` (``w``); it forwards its methods here.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from pyqtgraph.Qt import QtCore

from app.capture.trigger import rms_slope

from . import state
from .model.reference import incomplete_frame_messages, maps_messages, pattern_mismatch_messages
from .model.region import profile_line_for
from .model.schedule import LIVE_TAB, timer_ms
from .model.staleness import derived_text, unmeasured_messages, view_staleness
from .model.status import camera_problem, status_texts

log = logging.getLogger(__name__)


def line_profile(data: np.ndarray, x: np.ndarray, y: np.ndarray, p0, p1):
    """Values of ``data`` along the segment ``p0 -> p1`` (both ``(x_mm, y_mm)``), bilinear.

    Parameters
    ----------
    data : ndarray, shape (rows, cols)
        Map sampled at column coordinates ``x`` (cols,) and row coordinates ``y`` (rows,), mm, uniform.
    p0, p1 : (float, float)
        Segment ends in mm.

    Returns
    -------
    distance_mm, values : ndarray
        Distance from ``p0`` along the segment (mm) and the sampled values (NaN outside the map
        or where the map is NaN). About two samples per grid step.
    """
    from scipy.ndimage import map_coordinates

    dx = (x[-1] - x[0]) / (len(x) - 1) if len(x) > 1 else 1.0
    dy = (y[-1] - y[0]) / (len(y) - 1) if len(y) > 1 else 1.0
    c0, r0 = (p0[0] - x[0]) / dx, (p0[1] - y[0]) / dy
    c1, r1 = (p1[0] - x[0]) / dx, (p1[1] - y[0]) / dy
    n = int(max(2, 2 * np.ceil(np.hypot(c1 - c0, r1 - r0)) + 1))
    t = np.linspace(0.0, 1.0, n)
    rows, cols = r0 + t * (r1 - r0), c0 + t * (c1 - c0)
    values = map_coordinates(np.asarray(data, np.float64), [rows, cols], order=1, mode="constant", cval=np.nan)
    values[(rows < -0.5) | (rows > data.shape[0] - 0.5) | (cols < -0.5) | (cols > data.shape[1] - 0.5)] = np.nan
    length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
    return t * length, values


def show_raw(w, frame, tab) -> None:
    """Camera frame ``frame`` (``(seq, image, host_ns)``, :meth:`LiveSession.latest_frame`) on tab ``tab``'s raw
    view, its latency noted (and the first frame's time after the window was created)."""
    seq, image, host_ns = frame
    if w.first_frame_s is None:
        w.first_frame_s = time.monotonic() - w._t_created
        log.info("first camera frame on screen %.2f s after the window was created", w.first_frame_s)
    w._draw_raw(image, tab, host_ns, seq)
    w.latency_ms = (time.monotonic_ns() - host_ns) / 1e6 if host_ns else float("nan")


def look_again(w) -> None:
    """Between two ticks, after one that found no camera frame newer than the one on screen
    (:meth:`DrawClock.retry_s`): the newest frame if one has come meanwhile; then the timer to the next tick."""
    w._retry_armed = False
    try:
        seq = w.session.newest_seq()
        if not (w.pause_box.isChecked() or w.frozen) and seq is not None and seq != w.clock.last_raw_seq:
            frame = w.session.latest_frame()  # copied only when newer
            if frame is not None and w.clock.plan_retry(frame[0]):
                show_raw(w, frame, w.tabs.currentIndex())
                w.shown_rate.add(time.monotonic())
    except Exception:  # noqa: BLE001 - a drawing bug must not stop the display
        log.exception("display of a late camera frame failed")
    finally:
        if not w._closing:
            w._display_timer.start(timer_ms(w.clock.wait_s(time.perf_counter())))


def draw_raw(w, image, tab, host_ns=0, seq=None):
    bits = w._bit_depth()
    top = float((1 << bits) - 1)
    view = w.raw_view if tab == 0 else w.align_raw_view
    # auto: the sensor's full range (saturation visible at a glance); a typed range is kept
    view.set_data(image, levels=(0.0, top) if view.auto_levels else None, stamp_ns=host_ns, frame_id=seq)
    w._raw_shown = w._shown_now(seq, host_ns)
    view.set_stale(None)
    if tab == 0:
        k = view.stride
        sub = image[::k, ::k] if k > 1 else image
        mask = (sub >= top).view(np.uint8)
        # no saturated pixel: the overlay is hidden rather than drawn transparent (its alpha-blended
        # image made every paint of the raw view 3.5-4.4 instead of 2.9 ms at 512^2: docs/acquisition.md)
        saturated = bool(mask.any())
        w.saturation_overlay.setVisible(saturated)
        if saturated:
            w.saturation_overlay.setImage(mask, autoLevels=False, levels=(0, 1))
            if w.saturation_overlay.width() != sub.shape[1] or not w._overlay_rect == (image.shape, k):
                w.saturation_overlay.setRect(QtCore.QRectF(0, 0, image.shape[1], image.shape[0]))
                w._overlay_rect = (image.shape, k)
        p = w.session.worker.latest()
        sat = p.saturation_pct if p is not None else 0.0
        w._hist_count += 1
        if w._hist_count % 6 == 0:  # ~10 Hz is plenty for a histogram
            w.histogram.set_image(image, bits, sat)


def draw_result(w, p, part: int = -1):
    """Draw the maps of ``p``: part 0 height, profile, mask; part 1 displacement and slopes; -1 all."""
    r = p.result
    views = w.map_views
    if r is None:
        if part in (0, -1):
            # the full text on the height map; the small maps say what happened in a few words
            text, short = unmeasured_messages(p.error, w.session.worker.reconstructor is not None,
                                              w.reference_refused)
            for v in views:
                v.show_message(text, None if v is w.height_view else short)
            w._unmeasured = p  # the maps on screen (if any) are older than this frame: stale
            w._update_staleness()
        return
    x, y = r.x_mm, r.y_mm
    seq = p.seq
    if part in (0, -1):
        # "" unless the pattern is not the one chosen, or the frame came incomplete off the camera's link
        text, short = maps_messages(pattern_mismatch_messages(w.pattern_problem),
                                    incomplete_frame_messages(w.session.incomplete_pct_of(seq)))
        for v in views:
            v.show_message(text, None if v is w.height_view else short)
        w.last_drawn = p
        w.pin_overlay.update(r, p.light_bands)
        w._unmeasured = None
        w._maps_shown = w._shown_now(seq, p.host_timestamp_ns)
        height_um = np.multiply(r.height, 1e3, dtype=np.float32)
        w.height_view.set_data(height_um, x=x, y=y, stamp_ns=p.host_timestamp_ns, frame_id=seq)
        w.valid_view.set_data(r.valid.astype(np.float32), x=x, y=y, levels=(0.0, 1.0), frame_id=seq)
        w._draw_profile(height_um, x, y)
        w.profile_view.frame_id = seq
        w.probe_view.update(p)
    if part in (1, -1):
        u = r.displacement
        w.disp_view.set_data(np.hypot(u[0], u[1]).astype(np.float32), x=x, y=y, frame_id=seq)
        w.slope_x_view.set_data(np.multiply(r.slope_x, 1e3, dtype=np.float32), x=x, y=y, frame_id=seq)
        w.slope_y_view.set_data(np.multiply(r.slope_y, 1e3, dtype=np.float32), x=x, y=y, frame_id=seq)
        w.rms_history.add(rms_slope(r.slope_x, r.slope_y), seq)  # what the auto-trigger compares
        if not w.height_view.is_stale:
            for v in views:
                v.set_stale(None)


def draw_profile(w, height_um, x, y):
    if len(x) > 1 and len(y) > 1:
        extent = (float(x[0]), float(x[-1]), float(y[0]), float(y[-1]))
        if w._profile_placed != extent:  # the first maps, or maps of another extent (a new ROI)
            ends = profile_line_for(w.profile_roi.ends(), w._profile_placed, extent, float(y[len(y) // 2]))
            if ends is not None:
                w.profile_roi.set_ends(*ends)
            w._profile_placed = extent
    p0, p1 = w.profile_roi.ends()
    distance_mm, values = line_profile(height_um, x, y, p0, p1)
    w.profile_line_mm = (p0, p1)
    w.profile_view.set_profile(distance_mm, values, y_range=w.height_view.levels)


def draw_alignment(w, p):
    a = p.alignment
    if a is None:
        return
    r = p.result
    if (isinstance(a, dict) and "frame_change_rad" not in a and r is not None
            and np.shape(getattr(r, "phase", None))[1:] == np.shape(r.valid)):  # (dots: no carrier phase)
        # against the reference: the measured carrier phase's change between alignment updates (model: FrameMotion)
        change = w.result_motion.phases(r.phase, r.valid, run=id(w.reference))
        a = a if change is None else dict(a, frame_change_rad=change)
    w._align_shown = w._shown_now(p.seq, p.host_timestamp_ns)
    for v in (w.spectrum_view, w.modulation_view):
        v.set_stale(None)
    if p.spectrum is not None:
        w._draw_spectrum(p.spectrum)
    mod = a.get("modulation") if isinstance(a, dict) else None
    if mod is None and isinstance(a, dict) and "dot_size_px" in a and p.image is not None:
        # Reconstructor.alignment of dots has no contrast map: the live frame's, as before the reference
        from .alignment import DOT_WINDOW_PX, modulation_map

        mod, rows, cols = modulation_map(p.image, window_px=DOT_WINDOW_PX, step_px=DOT_WINDOW_PX // 2)
        a = dict(a, modulation=mod, modulation_rows_px=rows, modulation_cols_px=cols)
    if mod is not None:
        w.modulation_view.set_data(np.asarray(mod, np.float32), x=a.get("modulation_cols_px"),
                                      y=a.get("modulation_rows_px"), levels=(0.0, 1.0))
    ready, reasons, lines, notes = w.assess_alignment(a, p.saturation_pct)
    w.alignment_ready = ready
    w.alignment_metrics = dict(lines)
    lines = lines + [("note", n) for n in notes]
    if ready:
        w.ready_label.setText("READY TO MEASURE")
        w.ready_label.setStyleSheet("background:#d8f5d8; color:#060; font-size:22px; font-weight:bold;"
                                       "border:2px solid #060")
    else:
        w.ready_label.setText("NOT READY: " + "; ".join(reasons))
        w.ready_label.setStyleSheet("background:#fff0d0; color:#930; font-size:16px; font-weight:bold;"
                                       "border:2px solid #c60")
    w.metrics_label.setToolTip(a.get("error") or "")  # the table shortens a long problem
    w.metrics_label.setText("<table cellpadding=3>" + "".join(
        f"<tr><td>{k}</td><td><b>{v}</b></td></tr>" for k, v in lines) + "</table>")


def draw_spectrum(w, spec):
    get = (lambda k, d=None: spec.get(k, d)) if isinstance(spec, dict) else \
        (lambda k, d=None: getattr(spec, k, d))
    mag = get("log_magnitude")
    if mag is None:
        mag = get("magnitude")
    if mag is None and isinstance(spec, np.ndarray):
        mag = spec
    if mag is None:
        return
    fx, fy = get("freq_x"), get("freq_y")
    carriers = get("carriers_cycles_per_px") or get("carriers") or ()
    try:
        pts = [(float(c[0]), float(c[1])) for c in carriers]
    except Exception:  # noqa: BLE001
        pts = []
    w.spectrum_view.set_spectrum(mag, fx, fy, pts)


def _last_on_gpu(processed):
    """Where the newest live result was computed (None before the first): see status_texts."""
    if processed is None or processed.result is None:
        return None
    from processing.gpu import ran_on_gpu

    return ran_on_gpu(processed.result)


def update_status(w):
    """The status bar (texts from model/status.py), the stale marks, the recording panel; 4 times a second."""
    st = w.session.status()
    worker = w.session.worker
    lab = w.status_labels
    now = time.monotonic()
    # rates fall to 0 when nothing new arrives (a lost camera keeps its last measured rate otherwise)
    rec = worker.reconstructor  # where the live maps are computed: the GPU only when asked for
    t = status_texts(st, camera_fps=w.rates.rate("camera", w._frames_acquired(), st.get("camera_fps", 0.0), now),
                     processed_fps=w.rates.rate("processed", worker.processed, worker.fps, now),
                     shown_fps=w.displayed_fps, frozen=w.pause_box.isChecked() or w.frozen,
                     camera_open=w.session.acquisition is not None, display_skipped=worker.skipped,
                     latency_ms=w.latency_ms, device_text=getattr(rec, "device_text", "") if rec is not None else "",
                     reconstructed_in=worker.reconstructed_in, process_error=worker.process_error or "",
                     last_on_gpu=_last_on_gpu(worker.latest()), process_starting=worker.process_starting)
    lab["camera"].setText(t.camera)
    lab["camera"].setStyleSheet("padding: 0 4px; color: #c00000; font-weight: bold" if t.camera_lost
                                else "padding: 0 4px")
    lab["fps"].setText(t.fps)
    w.camera_fps_shown = t.camera_fps
    lab["drops"].setText(t.drops_tip, shown=t.drops)  # every counter in the tooltip
    style = "padding: 0 4px; color: #c00000; font-weight: bold" if t.drops_alarm else "padding: 0 4px"
    if lab["drops"].styleSheet() != style:
        lab["drops"].setStyleSheet(style)
    lab["ring"].setText(t.ring)
    lab["ring"].setToolTip(t.ring_tip)
    lab["latency"].setText(t.latency)
    lab["device"].setText(t.device)
    lab["device"].setToolTip(t.device_tip)
    style = "padding: 0 4px; color: #c00000" if t.device_failed else "padding: 0 4px"
    if lab["device"].styleSheet() != style:
        lab["device"].setStyleSheet(style)
    w._update_staleness()
    problem = camera_problem(st.get("error"), w.session.camera_id, w._shown_camera_error)
    if problem is not None:
        w._shown_camera_error = st.get("error")
        w.show_error(problem)
    lab["state"].setText(t.state)
    w._update_recording()
    for label in lab.values():  # an empty label takes no room (the state's kept 43 px from the others at 1280)
        if label.isVisibleTo(w) != bool(label.text()):
            label.setVisible(bool(label.text()))


def update_staleness(w) -> None:
    """Grey out and label every view whose data is not the newest the camera gave (ages refreshed 4x/s)."""
    if w.pause_box.isChecked() or w.frozen:
        state.update_truth(w)  # the user froze the views on purpose (the tank's progress still shows)
        return
    unmeasured = w._unmeasured
    w.stale = view_staleness(
        time.monotonic_ns(), w.session.acquisition, raw=w._raw_shown, maps=w._maps_shown,
        alignment=w._align_shown, unmeasured_seq=None if unmeasured is None else unmeasured.seq,
        frame_rate_hz=getattr(w.session.camera_settings(), "frame_rate_hz", None),
        camera_key=w._camera_key(),
        reference_key=w.references.key(w.session.worker.reconstructor is not None),
        maps_drawn=w.tabs.currentIndex() == LIVE_TAB, newest_seq=w.session.newest_seq())
    for v in (w.raw_view, w.align_raw_view):
        v.set_stale(w.stale.raw)
    for v in (*w.map_views, w.profile_view, w.probe_view):
        v.set_stale(w.stale.maps)
    w.pin_overlay.set_stale(w.stale.maps is not None)  # its words on the live raw frame are the maps'
    for v in (w.spectrum_view, w.modulation_view):
        v.set_stale(w.stale.alignment)
    rp = w.recording_panel  # the auto-trigger's quantity, from the maps on screen: their age too
    # measured on the slope maps, which are drawn one tick after the height when the maps go in two halves
    # (draw_result's second half): the frame to compare with is theirs, or the readout would be "stale" on
    # every other tick of live maps
    text, old = derived_text(w.rms_history.readout(), w.stale.maps, measured_seq=w.rms_history.seq,
                             maps_seq=w.slope_x_view.frame_id)
    rp.rms_label.setText(text)
    rp.rms_label.setStyleSheet("color: #888" if old else "")
    state.update_truth(w)  # "vs truth" with the same mark as the maps, whoever refreshed it


def finish_drawing(w) -> None:
    """Draw the second half (displacement, slopes) of the result whose first half is on screen, if one
    waits for its tick: Pause and a snapshot hold or store one frame's maps, each with its own range."""
    pending = w.clock.take_second_half()
    if pending is not None:
        w._draw_result(pending, part=1)


def pause_toggled(w, paused: bool) -> None:
    """Pause: finish drawing the maps of the frame on screen and show its raw frame, so all views show one frame."""
    views = (*w.map_views, w.raw_view, w.profile_view)
    if not paused:
        for v in views:
            v.show_paused(None)
        return
    finish_drawing(w)
    p = w.last_drawn
    if p is not None and w.raw_view.frame_id != p.seq and p.image is not None \
            and not w.raw_view.is_stale:
        w._draw_raw(p.image, 0, p.host_timestamp_ns, p.seq)
    for v in views:
        if v.frame_id is not None:
            v.show_paused(f"PAUSED: frame {v.frame_id}")
    if p is not None:
        w.info(f"display paused on frame {p.seq}: the raw frame and every map show that frame")
