"""``tirdeflect cameras`` and ``tirdeflect record``: headless listing and recording.

``app/cli/main.py`` builds the parsers with :func:`add_cameras_arguments` /
:func:`add_record_arguments` and calls :func:`cmd_cameras` / :func:`cmd_record`.
Also runnable alone: ``python3 -m app.cli.record record --camera synthetic --frames 100 --out x.h5``.

Exit codes of ``record`` (docs/reliability.md lists the cases):

* 0 -- every planned frame is in the file, complete;
* 1 -- the file was written but frames are missing (camera frame-id gaps or
  ring overruns) or incomplete (packets lost on the network: the pixels that
  arrived are kept, the frame table says how many bytes are missing); the
  summary says which ("12 of 200 frames incomplete"); also when the trigger came
  before all pre-trigger frames were captured. Timestamp gaps alone
  are reported as a suspicion, not counted, because a late frame makes one too;
* 2 -- error: bad arguments (checked before a camera is opened), camera busy
  or lost, disk full ... One line on stderr saying what to do; a partial
  file, if any, is valid up to the frame count the summary prints (frames
  captured before a trigger came are kept too); a file without a frame is
  deleted;
* 130 -- Ctrl-C, 143 -- SIGTERM, 129 -- SIGHUP: the frames already captured
  (burst frames in RAM too) are written, the file is closed with its summary.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from app.stop_signals import STOP_SIGNALS

__all__ = ["add_cameras_arguments", "cmd_cameras", "add_record_arguments", "cmd_record", "main"]

log = logging.getLogger("tirdeflect.record")


# ------------------------------------------------------------------ cameras
def add_cameras_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tirdeflect cameras``."""
    parser.add_argument("--timeout-s", type=float, default=3.0,
                        help="longest discovery time per backend, seconds (default 3)")
    parser.add_argument("--include-fake", action="store_true",
                        help="also list Aravis' in-process fake camera (aravis:Fake_1)")


def cmd_cameras(args) -> int:
    """Print one line per camera drivers.list_cameras() finds: id, backend, vendor, model, serial, address."""
    import drivers

    if not (args.timeout_s > 0 and math.isfinite(args.timeout_s)):  # -1 listed nothing and said nothing of it
        print(f"tirdeflect cameras: error: --timeout-s must be > 0 seconds; got {args.timeout_s:g}", file=sys.stderr)
        return 2
    try:
        cams = drivers.list_cameras(timeout_s=args.timeout_s, include_fake=args.include_fake)
    except Exception as exc:  # list_cameras promises not to fail; be loud if it does
        print(f"tirdeflect cameras: error: discovery failed: {exc}", file=sys.stderr)
        return 2
    width = max([len(c.camera_id) for c in cams] + [9])
    print(f"{'camera id':<{width}}  backend    vendor / model / serial / address")
    for c in cams:
        extra = " / ".join(x for x in (c.vendor, c.model, c.serial, c.address) if x)
        print(f"{c.camera_id:<{width}}  {c.backend:<9}  {extra}")
    return 0


# ------------------------------------------------------------------- record
def _roi(text: str):
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--roi takes X,Y,WIDTH,HEIGHT in pixels, e.g. 0,0,1024,1024; got {text!r}")
    return x, y, w, h


def _region(text: str):
    try:
        r0, r1, c0, c1 = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--region takes ROW0,ROW1,COL0,COL1 in pixels; got {text!r}")
    return r0, r1, c0, c1


def add_record_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tirdeflect record``."""
    from app.capture.trigger import TRIGGER_SOURCES

    p = parser
    p.add_argument("--camera", default="synthetic",
                   help="camera id: synthetic, aravis:Fake_1, aravis:127.0.0.1, gentl:/path/x.cti:DEVICE "
                        "(see 'tirdeflect cameras'; default synthetic: a ray-traced scene)")
    p.add_argument("--out", required=True, help="output HDF5 file; never overwritten")
    p.add_argument("--auto-name", action="store_true",
                   help="if --out exists, write NAME-001.h5 (next free number) instead of failing")
    n = p.add_argument_group("length (either --frames, or --pre/--post with a trigger)")
    n.add_argument("--frames", type=int, help="record this many frames from the start, no trigger")
    n.add_argument("--pre", type=int, help="frames before the trigger frame")
    n.add_argument("--post", type=int, help="frames from the trigger frame on (it included)")
    n.add_argument("--pre-s", type=float, help="pre-trigger length in seconds instead of frames")
    n.add_argument("--post-s", type=float, help="post-trigger length in seconds instead of frames")
    t = p.add_argument_group("trigger")
    t.add_argument("--trigger", default="software", choices=TRIGGER_SOURCES,
                   help="software: trigger once the pre-trigger frames are buffered (or after --trigger-after-s); "
                        "genicam: camera in trigger mode, one TriggerSoftware per frame at --frame-rate-hz; "
                        "lineN: hardware line makes the frames (pre must be 0); "
                        "auto: RMS slope in --region above --threshold (needs processing)")
    t.add_argument("--trigger-after-s", type=float, default=None,
                   help="software/genicam: fire the trigger this many seconds after recording starts")
    t.add_argument("--activation", default="RisingEdge", help="line trigger edge (RisingEdge, FallingEdge)")
    t.add_argument("--trigger-timeout-s", type=float, default=60.0,
                   help="give up when no trigger came within this time (line, auto), seconds")
    t.add_argument("--threshold", type=float, default=0.002, help="auto: RMS slope threshold (dimensionless)")
    t.add_argument("--region", type=_region, default=None, help="auto: ROW0,ROW1,COL0,COL1 of the slope map")
    t.add_argument("--geometry", help="geometry TOML (stored in the file; auto-trigger needs it)")
    t.add_argument("--reference", help="reference image (stored in the file; auto-trigger uses it)")
    c = p.add_argument_group("camera settings")
    c.add_argument("--exposure-us", type=float)
    c.add_argument("--gain-db", type=float)
    c.add_argument("--frame-rate-hz", type=float)
    c.add_argument("--pixel-format", choices=("Mono8", "Mono10", "Mono12", "Mono16"))
    c.add_argument("--roi", type=_roi, help="X,Y,WIDTH,HEIGHT in pixels")
    c.add_argument("--synthetic-size", type=int, default=512,
                   help="synthetic camera: frame size in pixels (square, default 512)")
    c.add_argument("--synthetic-frames", type=int, default=16,
                   help="synthetic camera: ray-traced frames in the loop (about 0.5 s each to render at 512)")
    b = p.add_argument_group("buffers")
    b.add_argument("--ring-frames", type=int, help="ring buffer size in frames (default: the whole capture "
                                                   "if it fits in memory, else 1 GB)")
    b.add_argument("--burst", dest="burst", action="store_true", default=None,
                   help="capture into RAM first, write afterwards (when the disk is slower than the camera)")
    b.add_argument("--no-burst", dest="burst", action="store_false", help="write while capturing")
    b.add_argument("--no-space-check", action="store_true", help="skip the free-space check (not advised)")
    o = p.add_argument_group("output")
    o.add_argument("--no-progress", action="store_true", help="no progress bar")
    o.add_argument("--timeout-s", type=float, default=None,
                   help="longest recording time after the trigger, seconds (default: 3x the planned duration + 30)")


class _UsageError(Exception):
    pass


def _plan(args):
    """"frames" or "trigger" from the arguments, every number checked; raises _UsageError (no camera is opened)."""
    def need(value, ok, name, rule):
        if value is not None and not ok(value):
            raise _UsageError(f"{name} must be {rule}; got {value:g}")

    need(args.frames, lambda v: v >= 1, "--frames", ">= 1")
    need(args.pre, lambda v: v >= 0, "--pre", ">= 0 frames")
    need(args.post, lambda v: v >= 1, "--post", ">= 1 frame (the trigger frame itself)")
    need(args.pre_s, lambda v: v >= 0, "--pre-s", ">= 0 seconds")
    need(args.post_s, lambda v: v > 0, "--post-s", "> 0 seconds")
    need(args.ring_frames, lambda v: v >= 2, "--ring-frames", ">= 2")
    need(args.timeout_s, lambda v: v > 0, "--timeout-s", "> 0 seconds")
    need(args.trigger_timeout_s, lambda v: v > 0, "--trigger-timeout-s", "> 0 seconds")
    need(args.trigger_after_s, lambda v: v >= 0, "--trigger-after-s", ">= 0 seconds")
    need(args.frame_rate_hz, lambda v: v > 0, "--frame-rate-hz", "> 0 Hz")
    need(args.exposure_us, lambda v: v > 0, "--exposure-us", "> 0 microseconds")
    need(args.synthetic_size, lambda v: v >= 16, "--synthetic-size", ">= 16 pixels")
    need(args.synthetic_frames, lambda v: v >= 1, "--synthetic-frames", ">= 1")
    if args.roi is not None and (min(args.roi[:2]) < 0 or min(args.roi[2:]) < 1):
        raise _UsageError(f"--roi needs X,Y >= 0 and WIDTH,HEIGHT >= 1 pixels; got {','.join(map(str, args.roi))}")
    if args.pre is not None and args.pre_s is not None:
        raise _UsageError("give either --pre (frames) or --pre-s (seconds), not both")
    if args.post is not None and args.post_s is not None:
        raise _UsageError("give either --post (frames) or --post-s (seconds), not both")
    if args.frames is not None:
        if any(v is not None for v in (args.pre, args.post, args.pre_s, args.post_s)):
            raise _UsageError("give either --frames N, or --pre/--post (with --trigger), not both")
        return "frames"
    if args.post is None and args.post_s is None:
        raise _UsageError("say how much to record: --frames N, or --pre N --post M (--pre-s/--post-s in seconds)")
    if args.trigger == "auto" and args.geometry is None and args.camera != "synthetic":
        # only the synthetic scene brings its own optics; asked after the camera, a file was left behind
        raise _UsageError("--trigger auto needs --geometry FILE.toml (slopes need the optics)")
    return "trigger"


def _frame_counts(args, mode: str, rate) -> tuple:
    """(pre, post) in frames; seconds need the frame rate (``rate``, Hz)."""
    from app.capture.trigger import frames_for_seconds

    if mode == "frames":
        return 0, int(args.frames)
    pre = frames_for_seconds(args.pre_s, rate, "--pre-s") if args.pre_s is not None else int(args.pre or 0)
    post = frames_for_seconds(args.post_s, rate, "--post-s") if args.post_s is not None else int(args.post)
    return pre, post


#: share of the available memory the ring buffer may take by default, and its cap in bytes
RING_MEMORY_FRACTION = 0.5
RING_MEMORY_CAP_BYTES = 8 * 10**9


def _ring_frames(args, mode: str, pre: int, post: int, shape, dtype) -> int:
    """Ring size in frames; refuses (_UsageError, naming the RAM) what must sit in RAM but cannot.

    The pre-trigger frames (and with --burst the whole capture) live in the
    ring, in RAM, before anything is written.
    """
    from app.capture.ringbuffer import RingBuffer, available_memory_bytes, format_bytes

    total = pre + post
    if args.ring_frames:
        ring_frames = int(args.ring_frames)
        needed = RingBuffer.bytes_for(shape, dtype, ring_frames)
        avail = available_memory_bytes()
        if needed > 0.8 * avail:
            raise _UsageError(f"--ring-frames {ring_frames} of {shape[0]}x{shape[1]} {np.dtype(dtype)} needs "
                              f"{format_bytes(needed)} of RAM but {format_bytes(avail)} are available; give fewer")
    else:
        avail = available_memory_bytes()
        budget = min(int(RING_MEMORY_FRACTION * avail), RING_MEMORY_CAP_BYTES)
        fit = RingBuffer.frames_for(shape, dtype, budget)
        ring_frames = max(min(total + 16, fit), min(fit, 8))
        if ring_frames < min(total, 64):
            ring_frames = min(fit, 64)
    in_ram = total if args.burst else pre + 1
    what = (f"--burst of {total} frames" if args.burst else f"{pre} pre-trigger frames (--pre)")
    if in_ram > ring_frames:
        need = RingBuffer.bytes_for(shape, dtype, in_ram)
        if args.ring_frames:
            limit = f"the ring of --ring-frames {ring_frames}"
        else:
            limit = (f"the RAM the ring may use, {format_bytes(budget)} ({ring_frames} frames; "
                     f"{RING_MEMORY_FRACTION:.0%} of the {format_bytes(avail)} available, at most "
                     f"{format_bytes(RING_MEMORY_CAP_BYTES)})")
        raise _UsageError(f"{what} of {shape[1]}x{shape[0]} {np.dtype(dtype)} must be held in RAM "
                          f"({format_bytes(need)}) but exceed {limit}; "
                          + ("record without --burst" if args.burst else "use fewer pre-trigger frames")
                          + (f" or give --ring-frames {in_ram}" if args.ring_frames else ", or a smaller --roi"))
    return ring_frames


def _check_out_creatable(out: Path) -> None:
    """Refuse, before a camera is opened, an --out where no file can be created (read-only,
    permission denied, ``/proc``): the recording failed only then, with HDF5's own text."""
    from app.files.h5safe import OutputLocationError, check_creatable

    try:
        check_creatable(out, "choose another --out (a folder you can write to)")
    except OutputLocationError as exc:
        raise _UsageError(str(exc)) from None


def _open_camera(args):
    """(camera, reference_image or None, geometry_toml or None)."""
    import drivers

    if args.camera == "synthetic":
        try:
            from app.capture.scene import open_synthetic_camera

            size = int(args.synthetic_size)
            rate = args.frame_rate_hz or 100.0
            cam, ref, geom, _ = open_synthetic_camera((size, size), args.synthetic_frames, rate)
            return cam, ref, geom.to_toml_text()
        except ImportError as exc:  # processing not available: built-in checkerboard
            log.warning("ray-traced scene unavailable (%s); using the built-in checkerboard", exc)
            return drivers.open_camera("synthetic"), None, None
    return drivers.open_camera(args.camera), None, None


def _configure(cam, args):
    values = {}
    if args.roi is not None:
        x, y, w, h = args.roi
        cur = cam.settings()
        values = dict(width=w, height=h)
        # offsets only when they change: some cameras have no OffsetX/OffsetY at all
        if x != cur.offset_x:
            values["offset_x"] = x
        if y != cur.offset_y:
            values["offset_y"] = y
    for name in ("exposure_us", "gain_db", "frame_rate_hz", "pixel_format"):
        v = getattr(args, name)
        if v is not None:
            values[name] = v
    if values:
        cam.configure(**values)


def _check_pixel_format(settings, args) -> None:
    """Refuse, before the file is created, a camera left in a pixel format that cannot be recorded (colour,
    packed): the camera then failed to start with the driver's advice in API words (``configure(...)``)."""
    from drivers.genicam_util import PIXEL_BITS

    if settings.pixel_format in PIXEL_BITS:
        return
    how = ("the camera did not keep --pixel-format " + args.pixel_format if args.pixel_format
           else "give --pixel-format")
    raise _UsageError(f"camera {args.camera!r} is set to pixel format {settings.pixel_format!r}, which cannot be "
                      f"recorded (mono only: {', '.join(PIXEL_BITS)}); {how}, e.g. --pixel-format Mono8")


def _progress(args, total: int, desc: str):
    """The bar, on stderr whatever it is (a terminal or a log the user reads as it grows); it turns itself off
    when its stream goes away (:mod:`app.progress`): the recording never depends on it."""
    from app.progress import progress_bar

    desc = desc + (" (captured into RAM)" if args.burst else "")
    return progress_bar(total, desc=desc, terminal_only=False, disable=args.no_progress, dynamic_ncols=True,
                        leave=True)


def _wait_with_bar(waitable, bar, counter, deadline: float, interval_s: float = 0.2) -> bool:
    shown = 0
    while True:
        done = waitable(interval_s)
        n = counter()
        if n > shown:
            bar.update(n - shown)
            shown = n
        if done:
            return True
        if time.monotonic() > deadline:
            return False


class _Signalled(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived: end like Ctrl-C (close the file properly), exit 128 + signal number."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _say(text: str, stream=None) -> None:
    """Print, but never fail: after SIGHUP the terminal may be gone (EIO) while the file is still being closed."""
    try:
        print(text, file=stream or sys.stdout, flush=True)
    except (OSError, ValueError):
        pass


def _install_stop_signals():
    """SIGTERM/SIGHUP raise _Signalled in the main thread; returns the previous handlers (to restore)."""
    def handler(signum, frame):
        _hold_stop_signals()  # a second signal must not cut the closing short
        raise _Signalled(signum)

    previous = {}
    for sig in STOP_SIGNALS:
        try:
            previous[sig] = signal.signal(sig, handler)
        except (ValueError, OSError):  # not the main thread: the caller handles it
            pass
    return previous


def _hold_stop_signals() -> None:
    """While the file is closed: SIGINT/SIGTERM/SIGHUP only print that closing goes on."""
    def busy(signum, frame):
        _say("tirdeflect record: still closing the file; please wait", sys.stderr)

    for sig in STOP_SIGNALS + (signal.SIGINT,):
        try:
            signal.signal(sig, busy)
        except (ValueError, OSError):
            pass


def _restore_signals(previous) -> None:
    for sig, h in previous.items():
        try:
            signal.signal(sig, h)
        except (ValueError, OSError, TypeError):
            pass
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    except (ValueError, OSError):
        pass


def cmd_record(args) -> int:
    """Record headless; print the drop summary. Returns the exit code (see module docstring)."""
    prog = "tirdeflect record"
    previous = _install_stop_signals()
    try:
        return _record(args, prog)
    except _Signalled as exc:  # came while the camera was being released: the file is already closed
        return 128 + exc.signum
    finally:
        _restore_signals(previous)


def _record(args, prog: str) -> int:
    from drivers.base import CameraError

    from app.capture.acquisition import Acquisition, AcquisitionError, dtype_for_bit_depth
    from app.capture.recorder import Recorder, RecorderError, format_summary
    from app.capture.ringbuffer import MemoryBudgetError
    from app.capture.trigger import AutoTrigger, TriggerError, TriggeredCapture, configure_trigger, threshold_attrs

    cam = acq = rec = cap = None
    result = None
    try:
        # everything that needs no camera is checked before one is opened
        mode = _plan(args)
        out = Path(args.out)
        if out.exists() and args.auto_name:
            from app.capture.recorder import unique_path

            out = unique_path(out)
        elif out.exists():
            raise _UsageError(f"{str(out)!r} already exists and recordings are never overwritten; "
                              "choose another --out or add --auto-name")
        if not out.parent.is_dir():
            raise _UsageError(f"folder {str(out.parent)!r} does not exist; create it or choose another --out")
        _check_out_creatable(out)
        if args.camera == "synthetic":  # its frames are known before the (slow) scene is rendered
            size = int(args.synthetic_size)
            _ring_frames(args, mode, *_frame_counts(args, mode, args.frame_rate_hz or 100.0), (size, size), np.uint8)
        elif args.roi is not None and (mode == "frames" or args.pre_s is None or args.frame_rate_hz):
            # at least one byte per pixel of the ROI
            _ring_frames(args, mode, *_frame_counts(args, mode, args.frame_rate_hz), args.roi[:1:-1], np.uint8)
        geometry_toml = Path(args.geometry).read_text() if args.geometry else None
        reference = None
        if args.reference:
            from app.files.imageio import read_image

            reference = read_image(args.reference)
        cam, scene_ref, scene_geom = _open_camera(args)
        if reference is None:
            reference = scene_ref
        if geometry_toml is None:
            geometry_toml = scene_geom
        _configure(cam, args)
        trig = args.trigger if mode == "trigger" else "software"
        configure_trigger(cam, trig, activation=args.activation)
        settings = cam.settings()
        _check_pixel_format(settings, args)
        rate = settings.frame_rate_hz or args.frame_rate_hz
        if trig == "genicam" and not rate:
            raise _UsageError("--trigger genicam needs --frame-rate-hz (how often to send TriggerSoftware)")
        pre, post = _frame_counts(args, mode, rate)
        total = pre + post
        shape = (settings.height, settings.width)
        dtype = dtype_for_bit_depth(settings.bit_depth)
        ring_frames = _ring_frames(args, mode, pre, post, shape, dtype)
        acq = Acquisition(cam, ring_frames=ring_frames, frame_rate_hz=rate if trig == "genicam" else None,
                          stall_timeout_s=5.0)
        # --auto-name: the name asked for, numbered when the file is made (another recording may take the
        # first free name meanwhile: three started at once, one failed)
        target = Path(args.out) if args.auto_name else out
        file_options = dict(check_space=not args.no_space_check, on_exists="rename" if args.auto_name else "error",
                            geometry_toml=geometry_toml, reference_image=reference)
        bar = _progress(args, total, out.name)
        duration = total / rate if rate else 10.0
        timeout = args.timeout_s if args.timeout_s is not None else 3 * duration + 30.0

        if mode == "frames":
            burst = bool(args.burst) and total <= acq.ring.n_frames
            rec = Recorder(acq.ring, target, n_frames=total, acquisition=acq, defer=burst,
                           attrs=dict(trigger_source="none", pre_frames=0, post_frames=total,
                                      frame_rate_hz=rate or -1.0, burst=int(burst)), **file_options)
            rec.begin(0)
            acq.stop_after(total - 1)
            acq.start()
            # burst: the bar counts frames captured into RAM (nothing is written before the end)
            counter = (lambda: min(acq.ring.head, total)) if burst else (lambda: rec.frames_written)
            finished = _wait_with_bar(rec.wait, bar, counter, time.monotonic() + timeout)
            summary_src = rec
        else:
            # the auto-trigger's threshold with its unit, as the window's recordings state it (--threshold is mm/mm)
            auto_attrs = threshold_attrs(1e3 * args.threshold) if trig == "auto" else {}
            cap = TriggeredCapture(acq, target, pre_frames=pre, post_frames=post, source=trig, burst=args.burst,
                                   attrs=auto_attrs, **file_options)
            rec = cap.recorder
            if trig == "genicam":
                acq.set_software_trigger_rate(rate)
            acq.start()
            t0 = time.monotonic()
            if trig in ("software", "genicam"):
                if args.trigger_after_s is not None:
                    acq.wait(args.trigger_after_s)
                else:  # as soon as the pre-trigger frames are in the ring
                    while not acq.ring.wait_for(pre, 0.2):
                        if acq.ring.closed or time.monotonic() - t0 > args.trigger_timeout_s:
                            break
                if acq.ring.closed and acq.error:
                    raise AcquisitionError(acq.error)
                cap.trigger_now()
            elif trig == "auto":
                _run_auto(args, acq, cap, geometry_toml, reference, AutoTrigger, t0)
            else:  # line: armed on the first frame; wait for it
                while not acq.ring.wait_for(0, 0.2):
                    if acq.ring.closed:
                        raise AcquisitionError(acq.error or "acquisition stopped before the first line trigger")
                    if time.monotonic() - t0 > args.trigger_timeout_s:
                        cap.cancel()
                        raise TriggerError(
                            f"no frame came within {args.trigger_timeout_s:g} s: no pulse on "
                            f"{settings.trigger_source} ({settings.trigger_activation}); check the wiring or "
                            "raise --trigger-timeout-s")
            finished = _wait_with_bar(cap.wait, bar, lambda: rec.frames_written, time.monotonic() + timeout)
            summary_src = cap
        bar.close()
        if not finished:
            late = f"recording did not finish within {timeout:g} s (--timeout-s)"
            rec.stop(10.0, drain=False, error=f"{late}; stopped there, the frames written until then are kept")
            _say(f"{prog}: error: {late}; the file holds {rec.frames_written} frames", sys.stderr)
            result = 2
        acq.stop(10.0)
        summary = summary_src.summary()
        if not (rec.error and rec.frames_written == 0):  # (then no file is kept: the error line says so)
            _say(format_summary(summary))
        if result is None:
            if rec.error:
                tail = _end_after_error(rec, cap, acq, rec.error) if rec.frames_written == 0 else ""
                _say(f"{prog}: error: {rec.error}{tail}", sys.stderr)
                result = 2
            else:
                result = exit_status(summary)
        return result
    except KeyboardInterrupt as exc:
        _hold_stop_signals()
        what = "closing the file" if rec is not None else "no recording had begun, no file was written"
        if isinstance(exc, _Signalled):
            name = signal.Signals(exc.signum).name
            _say(f"{prog}: {name} received; {what}", sys.stderr)
            code = 128 + exc.signum
        else:
            _say(f"{prog}: interrupted; {what}", sys.stderr)
            code = 130
        if rec is not None and rec.state == "recording":
            rec.stop(0.0, drain=True)  # before the camera stops: its end is then no error of the recording
        if acq is not None:
            try:
                acq.stop(5.0)
            except AcquisitionError:
                pass
        if rec is not None:
            by = 'Ctrl-C' if code == 130 else signal.Signals(code - 128).name
            _close_on_stop(rec, cap, f"stopped by {by}")
            if rec.frames_written == 0 and _drop_empty_file(rec):
                _say(f"{prog}: stopped by {by} before any frame was recorded; no file was written", sys.stderr)
            else:
                _say(format_summary(rec.summary()))
                _say(f"{prog}: stopped by {by}; the file holds {rec.frames_written} frames", sys.stderr)
        return code
    except (_UsageError, CameraError, AcquisitionError, RecorderError, TriggerError, MemoryBudgetError,
            ValueError, OSError) as exc:
        _say(f"{prog}: error: {exc}{_end_after_error(rec, cap, acq, exc)}", sys.stderr)
        return 2
    finally:
        if acq is not None and acq.state == "running":
            try:
                acq.stop(5.0)
            except AcquisitionError:
                pass
        if cam is not None:
            try:
                cam.close()
            except Exception:
                pass


def _close_on_stop(rec, cap, why: str, error: Optional[str] = None) -> None:
    """After Ctrl-C/SIGTERM/SIGHUP or an error: write every frame already captured, then close the file properly.

    Burst mode: the frames wait in RAM; they are written now. Before a
    trigger came, the pre-trigger frames in the ring are written (their
    ``trigger_index`` counts back from the stop, -N .. -1, while the file
    claims no trigger: no ``trigger_sequence``, no TRIGGER flag; a note in
    the file says ``why``); with none captured the
    file is deleted (``rec.state`` "cancelled"). ``error`` (None for the
    user's own stop): what went wrong, stored as the file's ``error``.
    """
    if rec.state == "armed" and cap is not None:
        ring = rec.ring
        start = max(ring.oldest, ring.head - cap.pre_frames)
        if ring.head <= start:
            cap.cancel()
            return
        if error:
            error = (f"{error}; it came before the trigger: the file holds only the {ring.head - start} "
                     "frames captured before it, no trigger frame")
        # the note first: the writer begun below may reach the stop and close the file (its events with it)
        # before this thread runs again (a loaded machine's test run lost the note so)
        rec.file.add_event("note", f"{why} before the trigger: the file holds the {ring.head - start} frames "
                                   "before it (trigger_index counts back from it; no trigger frame)",
                           sequence=ring.head)
        try:
            rec.begin(start, count_back_from=ring.head, stop_error=error, stop_at=ring.head)
        except Exception:
            pass
    rec.stop(60.0, drain=True, error=error)


def _end_after_error(rec, cap, acq, exc) -> str:
    """Close the recording after an error: keep what was captured (pre-trigger frames in RAM too), delete a
    file that holds no frame (it would block the name for the next try). Returns the tail of the error line
    (what became of the file); "" when no file was begun."""
    from app.capture.acquisition import AcquisitionError

    if rec is None:
        return ""
    if not rec.done:
        if acq is not None and rec.state == "armed":
            try:  # no frame may come after the error: those already in the ring are the recording
                acq.stop(5.0)
            except AcquisitionError:
                pass
        if cap is not None:
            _close_on_stop(rec, cap, f"error ({exc})", error=str(exc))
        else:
            rec.stop(30.0, drain=True, error=str(exc))
    if rec.frames_written == 0:
        if _drop_empty_file(rec):
            return "; no frame was recorded, no file was written"
        return f"; the file {str(rec.path)!r} holds no frame"
    return f"; the file {str(rec.path)!r} holds the {rec.frames_written} frames captured before it"


def _drop_empty_file(rec) -> bool:
    """Delete the file of an ended recording that holds no frame; True when no such file is left."""
    if not rec.done or rec.frames_written > 0:
        return False
    try:
        Path(rec.path).unlink()
    except FileNotFoundError:
        pass
    except OSError:
        return False
    return True


def exit_status(summary: dict) -> int:
    """0 all planned frames complete; 1 frames missing or incomplete (see the module docstring), pre-trigger
    frames missing too (the trigger came before they were captured)."""
    if 0 <= summary.get("pre_available", -1) < summary.get("pre_frames", 0):
        return 1
    return 1 if summary.get("total_missing", 0) or summary.get("incomplete", 0) else 0


def _run_auto(args, acq, cap, geometry_toml, reference, AutoTrigger, t0):
    """Feed the auto-trigger with slope maps of the newest frames until it fires (main thread)."""
    from app.capture.trigger import TriggerError

    if geometry_toml is None:
        raise TriggerError("--trigger auto needs --geometry FILE.toml (slopes need the optics)")
    try:
        from processing import Geometry, Reconstructor
    except ImportError as exc:
        raise TriggerError(f"--trigger auto needs the processing package: {exc}") from exc
    geometry = Geometry.from_toml_text(geometry_toml)
    ring = acq.ring
    if reference is None:
        first = None
        while first is None:
            first = ring.latest(0.5)
            if ring.closed or time.monotonic() - t0 > args.trigger_timeout_s:
                raise TriggerError("no frame for the auto-trigger's reference")
        reference = first.image
    recon = Reconstructor(reference, geometry)
    auto = AutoTrigger(args.threshold, args.region, dead_time_s=0.0, rearm=False, callback=cap.auto_callback(),
                       ready=cap.ready_for)
    while cap.trigger_sequence is None:
        if time.monotonic() - t0 > args.trigger_timeout_s:
            cap.cancel()
            raise TriggerError(f"auto-trigger did not fire within {args.trigger_timeout_s:g} s (last RMS slope "
                               f"{auto.last_rms:.3g}, threshold {args.threshold:g}); lower --threshold")
        fr = ring.latest(0.5)
        if fr is None:
            if ring.closed:
                raise TriggerError(f"camera stopped before the auto-trigger fired: {ring.error or 'stopped'}")
            continue
        res = recon(fr.image, grid="decimated")
        auto.feed(res.slope_x, res.slope_y, sequence=fr.sequence)


def main(argv: Optional[list] = None) -> int:
    """Stand-alone entry: ``python3 -m app.cli.record cameras|record ...``."""
    parser = argparse.ArgumentParser(prog="tirdeflect")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("cameras", help="list cameras")
    add_cameras_arguments(p)
    p.set_defaults(func=cmd_cameras)
    p = sub.add_parser("record", help="record frames to HDF5")
    add_record_arguments(p)
    p.set_defaults(func=cmd_record)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
