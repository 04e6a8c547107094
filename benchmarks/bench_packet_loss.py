"""Packet-loss accounting of a long GigE recording (issue 7: "every lost packet accounted for").

Run from the repository root (needs arv-fake-gv-camera-0.8)::

    python3 benchmarks/bench_packet_loss.py                       # 10 minutes at -r 2 (the goal)
    python3 benchmarks/bench_packet_loss.py --seconds 30 --loss 20
    python3 benchmarks/bench_packet_loss.py --seconds 60 --loss 20 --link   # a camera that resends

It holds the fake camera's machine-wide lock for the whole run (other
test runs that need the fake camera wait at most 120 s for it).

Starts the fake GigE camera dropping ``--loss`` packets per thousand, records
512x512 Mono8 at ``--rate-hz`` with ``tirdeflect record`` (a real subprocess)
and prints, from the file and the summary: frames complete / incomplete, the
bytes missing (per frame in ``frame_table.missing_bytes``), the data packets
that makes (bytes / packet payload), what the fake's loss rate predicts, the
resend requests Aravis sent and the packets the camera resent, the frame-id
gaps, and whether the file, the summary and the exit status agree. With
``--link`` the loss-free fake camera is reached through
:class:`tests.faults.lossy_link.LossyLink`, which loses the packets and
answers resend requests like a real camera (the fake itself never resends).
Short versions of the same checks are in tests/faults/test_packet_loss.py.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: IPv4 + UDP + GVSP headers of one GigE Vision data packet (standard ids), bytes
GVSP_OVERHEAD_BYTES = 36


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="recording length, s (default 600)")
    ap.add_argument("--loss", type=int, default=2, help="packets lost per thousand (the fake's -r; default 2)")
    ap.add_argument("--rate-hz", type=float, default=20.0, help="frame rate, Hz (default 20)")
    ap.add_argument("--link", action="store_true", help="lose the packets in a link that serves resend requests")
    args = ap.parse_args(argv)
    import contextlib

    from tests.drivers.fixtures import FakeGvCamera
    from tests.faults.lossy_link import LossyLink

    n_frames = int(round(args.seconds * args.rate_hz))
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(tempfile.TemporaryDirectory())
        fake = stack.enter_context(FakeGvCamera(loss_per_thousand=0 if args.link else args.loss))
        link = stack.enter_context(LossyLink(loss_per_thousand=args.loss)) if args.link else None
        camera_id = link.camera_id if link else fake.camera_id
        out = Path(tmp) / "loss.h5"
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "app.cli", "record", "--camera", camera_id, "--frames",
                               str(n_frames), "--frame-rate-hz", str(args.rate_hz), "--out", str(out),
                               "--no-progress"], cwd=ROOT, capture_output=True, text=True,
                              timeout=args.seconds * 3 + 120)
        took = time.monotonic() - t0
        with h5py.File(out, "r") as f:
            table = f["frame_table"][:]
            summary = json.loads(f["summary"].attrs["summary_json"])
            frame_bytes = f["frames"].shape[1] * f["frames"].shape[2] * f["frames"].dtype.itemsize
    stats = summary.get("camera_statistics", {})
    packet_size = 1400  # what Aravis' auto packet size chooses on loopback
    payload = packet_size - GVSP_OVERHEAD_BYTES
    packets_per_frame = math.ceil(frame_bytes / payload) + 2  # data + leader + trailer
    n = len(table)
    incomplete = (table["flags"] & 1) != 0
    missing = table["missing_bytes"]
    data_packets_lost = int(sum(math.ceil(m / payload) for m in missing if m))
    expected = n * packets_per_frame * args.loss / 1000 * (args.loss / 1000 if args.link else 1)
    where = f"link losing {args.loss}/1000 (serves resends)" if link else f"fake camera -r {args.loss}"
    print(f"{where}, {n} frames of {frame_bytes} bytes at {args.rate_hz:g} Hz "
          f"({took:.0f} s), exit status {proc.returncode}")
    print(f"  complete frames        {n - int(incomplete.sum())} of {n} ({100 * (1 - incomplete.mean()):.2f} %)")
    print(f"  incomplete frames      {int(incomplete.sum())} (summary: {summary['incomplete']})")
    print(f"  bytes missing          {int(missing.sum())} = {100 * missing.sum() / (n * frame_bytes):.3f} % "
          f"(summary: {summary['incomplete_missing_bytes']}; driver: {stats.get('n_missing_bytes')})")
    print(f"  data packets lost      {data_packets_lost} (at least; {payload} B each); the loss rate predicts "
          f"{expected:.0f} of all {n * packets_per_frame} packets lost" + (" twice" if link else ""))
    print(f"  leader/trailer only    {stats.get('n_failed_but_all_pixels')} frames (every pixel there, not flagged)")
    print(f"  resend requests        {summary.get('packets_resend_requests')}, packets resent "
          f"{summary.get('packets_resent')}" + (" (the fake camera never resends)" if not link else ""))
    if link:
        late = stats.get("n_duplicated_packets", 0) + stats.get("n_ignored_packets", 0)
        print(f"  link                   lost {link.dropped} of {link.forwarded + link.dropped} first sends, "
              f"resent {link.resent} ({link.resent_dropped} lost again); every first-send loss accounted: "
              f"{link.dropped} <= {stats.get('n_resent_packets', 0)} resent + {late} duplicated/late + "
              f"{data_packets_lost} missing: {link.dropped <= stats.get('n_resent_packets', 0) + late + data_packets_lost}")
    print(f"  frame-id gaps          {summary['lost_upstream_id_gaps']}, ring overruns {summary['lost_ring_overrun']}")
    agree = (summary["incomplete"] == int(incomplete.sum())
             and summary["incomplete_missing_bytes"] == int(missing.sum()) == stats.get("n_missing_bytes")
             and np.array_equal(incomplete, missing > 0)
             and proc.returncode == (1 if incomplete.any() or summary["total_missing"] else 0))
    print(f"  file, summary, driver and exit status agree: {agree}")
    line = [x for x in proc.stdout.splitlines() if "result" in x]
    print("  " + (line[0].strip() if line else "(no result line)"))
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
