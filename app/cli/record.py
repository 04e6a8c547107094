"""``tirdeflect cameras`` and ``tirdeflect record``: headless listing and recording.

``app/cli/main.py`` builds the parsers with :func:`add_cameras_arguments` /
:func:`add_record_arguments` and calls :func:`cmd_cameras` / :func:`cmd_record`.
Also runnable alone: ``python3 -m app.cli.record record --camera synthetic --frames 100 --out x.h5``.

Exit codes of ``record``: 0 every planned frame is in the file; 1 the file
was written but frames are missing (camera frame-id gaps or ring overruns;
the summary says which; timestamp gaps alone are reported as a suspicion,
not counted, because a late frame makes one too); 2 error (one
line on stderr saying what to do; a partial file, if any, stays valid);
130 interrupted (Ctrl-C; the file holds what was written).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Optional

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
    """(mode, pre, post, n) from the arguments; raises _UsageError with a clear message."""
    if args.frames is not None:
        if any(v is not None for v in (args.pre, args.post, args.pre_s, args.post_s)):
            raise _UsageError("give either --frames N, or --pre/--post (with --trigger), not both")
        if args.frames < 1:
            raise _UsageError(f"--frames must be >= 1; got {args.frames}")
        return "frames"
    if args.post is None and args.post_s is None:
        raise _UsageError("say how much to record: --frames N, or --pre N --post M (--pre-s/--post-s in seconds)")
    return "trigger"


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


def _progress(args, total: int, desc: str):
    if args.no_progress:
        return None
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return None
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=True)


def _wait_with_bar(waitable, bar, counter, deadline: float, interval_s: float = 0.2) -> bool:
    shown = 0
    while True:
        done = waitable(interval_s)
        if bar is not None:
            n = counter()
            if n > shown:
                bar.update(n - shown)
                shown = n
        if done:
            return True
        if time.monotonic() > deadline:
            return False


def cmd_record(args) -> int:
    """Record headless; print the drop summary. Returns the exit code (see module docstring)."""
    from drivers.base import CameraError

    from app.capture.acquisition import Acquisition, AcquisitionError
    from app.capture.recorder import Recorder, RecorderError, format_summary
    from app.capture.ringbuffer import MemoryBudgetError, RingBuffer, available_memory_bytes
    from app.capture.trigger import AutoTrigger, TriggerError, TriggeredCapture, configure_trigger

    prog = "tirdeflect record"
    cam = acq = rec = None
    result = None
    try:
        mode = _plan(args)
        out = Path(args.out)
        if out.exists() and args.auto_name:
            from app.capture.recorder import unique_path

            out = unique_path(out)
        elif out.exists():
            raise _UsageError(f"{str(out)!r} already exists and recordings are never overwritten; "
                              "choose another --out or add --auto-name")
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
        rate = settings.frame_rate_hz or args.frame_rate_hz
        if trig == "genicam" and not rate:
            raise _UsageError("--trigger genicam needs --frame-rate-hz (how often to send TriggerSoftware)")
        from app.capture.trigger import frames_for_seconds

        if mode == "frames":
            pre, post = 0, int(args.frames)
        else:
            pre = (frames_for_seconds(args.pre_s, rate, "--pre-s") if args.pre_s is not None else int(args.pre or 0))
            post = (frames_for_seconds(args.post_s, rate, "--post-s") if args.post_s is not None else int(args.post))
        total = pre + post
        shape = (settings.height, settings.width)
        from app.capture.acquisition import dtype_for_bit_depth

        dtype = dtype_for_bit_depth(settings.bit_depth)
        if args.ring_frames:
            ring_frames = int(args.ring_frames)
        else:
            budget = min(int(0.5 * available_memory_bytes()), 8 * 10**9)
            fit = RingBuffer.frames_for(shape, dtype, budget)
            ring_frames = max(min(total + 16, fit), min(fit, 8))
            if ring_frames < min(total, 64):
                ring_frames = min(fit, 64)
        acq = Acquisition(cam, ring_frames=ring_frames, frame_rate_hz=rate if trig == "genicam" else None,
                          stall_timeout_s=5.0)
        file_options = dict(check_space=not args.no_space_check, on_exists="error",
                            geometry_toml=geometry_toml, reference_image=reference)
        bar = _progress(args, total, out.name)
        duration = total / rate if rate else 10.0
        timeout = args.timeout_s if args.timeout_s is not None else 3 * duration + 30.0

        if mode == "frames":
            burst = bool(args.burst) and total <= acq.ring.n_frames
            if args.burst and not burst:
                raise _UsageError(f"--burst of {total} frames does not fit into the ring of {acq.ring.n_frames} "
                                  "frames; give --ring-frames or record without --burst")
            rec = Recorder(acq.ring, out, n_frames=total, acquisition=acq, defer=burst,
                           attrs=dict(trigger_source="none", pre_frames=0, post_frames=total,
                                      frame_rate_hz=rate or -1.0, burst=int(burst)), **file_options)
            rec.begin(0)
            acq.stop_after(total - 1)
            acq.start()
            finished = _wait_with_bar(rec.wait, bar, lambda: rec.frames_written, time.monotonic() + timeout)
            summary_src = rec
        else:
            cap = TriggeredCapture(acq, out, pre_frames=pre, post_frames=post, source=trig, burst=args.burst,
                                   **file_options)
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
        if bar is not None:
            bar.close()
        if not finished:
            rec.stop(10.0, drain=False)
            print(f"{prog}: error: recording did not finish within {timeout:g} s; the file holds "
                  f"{rec.frames_written} frames", file=sys.stderr)
            result = 2
        acq.stop(10.0)
        summary = summary_src.summary()
        print(format_summary(summary))
        if result is None:
            if rec.error:
                print(f"{prog}: error: {rec.error}", file=sys.stderr)
                result = 2
            else:
                result = 1 if summary.get("total_missing", 0) else 0
        return result
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; closing the file", file=sys.stderr)
        if acq is not None:
            try:
                acq.stop(5.0)
            except AcquisitionError:
                pass
        if rec is not None:
            rec.stop(30.0, drain=True)  # write what is in the ring, then close the file properly
            print(format_summary(rec.summary()))
        return 130
    except (_UsageError, CameraError, AcquisitionError, RecorderError, TriggerError, MemoryBudgetError,
            ValueError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
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
