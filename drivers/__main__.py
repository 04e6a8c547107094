"""``python3 -m drivers``: list cameras; ``python3 -m drivers --measure``: print driver figures.

The measurements use real endpoints only (synthetic camera, Aravis Fake_1,
the GigE Vision fake camera process on loopback, viky.cti) and print each
figure next to what was asked for.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time

import numpy as np

import drivers


def _list(args):
    for info in drivers.list_cameras(timeout_s=args.timeout_s, include_fake=args.include_fake):
        print(f"{info.camera_id:50s} {info.backend:9s} {info.vendor} {info.model} {info.serial} {info.address}")


def _synthetic():
    from drivers.synthetic import SyntheticCamera, moving_checkerboard

    frames = moving_checkerboard((1024, 1024), n_phases=8)
    with SyntheticCamera(frames, max_rate=True) as cam:
        cam.start()
        n = 20000
        t0 = time.perf_counter()
        for _ in range(n):
            f = cam.fetch(1.0)
        dt = time.perf_counter() - t0
        print(f"synthetic max_rate 1024x1024 Mono8: {n / dt:,.0f} fetches/s ({dt / n * 1e6:.1f} us each, zero-copy views)")
        dst = np.empty((1024, 1024), np.uint8)
        t0 = time.perf_counter()
        for _ in range(2000):
            np.copyto(dst, cam.fetch(1.0).image)
        dt = time.perf_counter() - t0
        print(f"  with a 1 MiB copy per frame (what a ring buffer does): {2000 / dt:,.0f} frames/s")
    for rate in (100.0, 500.0):
        with SyntheticCamera(frames, frame_rate_hz=rate) as cam:
            cam.start()
            got = [cam.fetch(1.0) for _ in range(int(rate) + 1)]
        host = np.array([g.host_timestamp_ns for g in got])
        measured = (len(got) - 1) / ((host[-1] - host[0]) * 1e-9)
        lat = np.array([g.host_timestamp_ns - g.timestamp_ns for g in got]) * 1e-6
        print(f"synthetic paced {rate:g} Hz over 1 s: measured {measured:.2f} Hz ({(measured / rate - 1) * 100:+.2f} %),"
              f" delivery after due time median {np.median(lat):.3f} ms, max {lat.max():.3f} ms")


def _aravis():
    from drivers import aravis
    from drivers.base import CameraLost, FetchTimeout

    if not aravis.available():
        print("aravis: bindings not available")
        return
    with aravis.AravisCamera("Fake_1") as cam:
        cam.configure(width=512, height=512, frame_rate_hz=200.0)
        cam.start()
        got = [cam.fetch(2.0) for _ in range(101)]
        host = np.array([g.host_timestamp_ns for g in got])
        print(f"aravis:Fake_1 512x512 at 200 Hz: {100 / ((host[-1] - host[0]) * 1e-9):.1f} Hz received, "
              f"ids contiguous: {bool(np.all(np.diff([g.frame_id for g in got]) == 1))}")
    exe = shutil.which("arv-fake-gv-camera-0.8")
    if exe is None:
        print("aravis GigE fake: arv-fake-gv-camera-0.8 not installed")
        return
    for loss in (0, 20):
        p = subprocess.Popen([exe, "-i", "127.0.0.1"] + (["-r", str(loss)] if loss else []),
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(0.3)  # measurement script, not a test: give the process a moment to bind
            with aravis.AravisCamera("127.0.0.1", n_buffers=64) as cam:
                cam.configure(width=64, height=64, frame_rate_hz=200.0)
                cam.start()
                got = [cam.fetch(2.0) for _ in range(400)]
                cam.stop()
                s = cam.statistics()
            ids = np.array([g.frame_id for g in got])
            print(f"aravis:127.0.0.1 GigE fake, -r {loss} (per mille packets lost), 400 frames 64x64 at 200 Hz: "
                  f"complete {s['n_completed_buffers']}, failed(incomplete, delivered flagged) {s['n_failures']}, "
                  f"id gaps {s['n_id_gap_frames']}, span {ids.max() - ids.min() + 1} = delivered {len(got)} + gaps; "
                  f"missing packets {s['n_missing_packets']}, resent {s['n_resent_packets']}, lost leaders {s['n_leader_lost']}")
            if loss == 0:
                with aravis.AravisCamera("127.0.0.1", n_buffers=32) as cam:
                    cam.configure(width=1024, height=1024, frame_rate_hz=100.0)
                    cam.start()
                    t0 = time.monotonic()
                    got = [cam.fetch(3.0) for _ in range(200)]
                    dt = time.monotonic() - t0
                    cam.stop()
                    s = cam.statistics()
                print(f"aravis:127.0.0.1 GigE fake 1024x1024 Mono8 asked 100 Hz: received {199 / dt:.1f} Hz, "
                      f"incomplete {s['n_incomplete_delivered']}, id gaps {s['n_id_gap_frames']}, "
                      f"missing packets {s['n_missing_packets']}")
                cam = aravis.AravisCamera("127.0.0.1", lost_timeout_s=1.0, probe_period_s=0.1).open()
                cam.configure(width=64, height=64)
                cam.start()
                cam.fetch(2.0)
                p.kill()
                t0 = time.monotonic()
                while True:
                    try:
                        cam.fetch(0.3)
                    except FetchTimeout:
                        continue
                    except CameraLost:
                        break
                t_lost = time.monotonic() - t0
                t1 = time.monotonic()
                cam.close()
                print(f"aravis GigE fake killed mid-stream: CameraLost after {t_lost:.2f} s "
                      f"(lost_timeout_s=1.0), close took {time.monotonic() - t1:.2f} s")
        finally:
            p.kill()
            p.wait()


def _gentl():
    from drivers import gentl

    cti = gentl.viky_cti()
    if cti is None:
        print("gentl: viky.cti not found")
        return
    for w, rate in ((800, 200.0), (320, 200.0), (320, 50.0)):
        with gentl.GenTLCamera(f"{cti}:0") as cam:
            cam.configure(pixel_format="Mono8", width=w, height=w, frame_rate_hz=rate)
            cam.start()
            got = [cam.fetch(2.0) for _ in range(int(rate) + 1)]
            s = cam.statistics()
        host = np.array([g.host_timestamp_ns for g in got])
        print(f"gentl viky.cti {w}x{w} Mono8 asked {rate:g} Hz: received {(len(got) - 1) / ((host[-1] - host[0]) * 1e-9):.1f} Hz, "
              f"id gaps {s['n_id_gap_frames']}, incomplete discarded by harvesters {s['n_incomplete_discarded']}")


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python3 -m drivers", description=__doc__.splitlines()[0])
    ap.add_argument("--measure", action="store_true", help="print driver figures instead of listing cameras")
    ap.add_argument("--timeout-s", dest="timeout_s", type=float, default=3.0)
    ap.add_argument("--include-fake", action="store_true", help="also list aravis:Fake_1")
    args = ap.parse_args(argv)
    if not args.measure:
        _list(args)
        return 0
    _synthetic()
    _aravis()
    _gentl()
    return 0


if __name__ == "__main__":
    sys.exit(main())
