"""Packet-loss accounting of a long GigE recording (issue 7: "every lost packet accounted for").

Run from the repository root (needs arv-fake-gv-camera-0.8)::

    python3 benchmarks/bench_packet_loss.py                       # 10 minutes at -r 2 (the goal)
    python3 benchmarks/bench_packet_loss.py --seconds 30 --loss 20

Starts the fake GigE camera dropping ``--loss`` packets per thousand, records
512x512 Mono8 at ``--rate-hz`` with ``tirdeflect record`` (a real subprocess)
and prints, from the file and the summary: frames complete / incomplete, the
bytes missing (per frame in ``frame_table.missing_bytes``), the data packets
that makes (bytes / packet payload), what the fake's loss rate predicts, the
resend requests Aravis sent and the packets the camera resent, the frame-id
gaps, and whether the file, the summary and the exit status agree. A short
version of the same checks is tests/faults/test_packet_loss.py.
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
    args = ap.parse_args(argv)
    from tests.drivers.fixtures import FakeGvCamera

    n_frames = int(round(args.seconds * args.rate_hz))
    with tempfile.TemporaryDirectory() as tmp, FakeGvCamera(loss_per_thousand=args.loss) as fake:
        out = Path(tmp) / "loss.h5"
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "app.cli", "record", "--camera", fake.camera_id, "--frames",
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
    expected = n * packets_per_frame * args.loss / 1000
    print(f"fake camera -r {args.loss}, {n} frames of {frame_bytes} bytes at {args.rate_hz:g} Hz "
          f"({took:.0f} s), exit status {proc.returncode}")
    print(f"  complete frames        {n - int(incomplete.sum())} of {n} ({100 * (1 - incomplete.mean()):.2f} %)")
    print(f"  incomplete frames      {int(incomplete.sum())} (summary: {summary['incomplete']})")
    print(f"  bytes missing          {int(missing.sum())} = {100 * missing.sum() / (n * frame_bytes):.3f} % "
          f"(summary: {summary['incomplete_missing_bytes']}; driver: {stats.get('n_missing_bytes')})")
    print(f"  data packets lost      {data_packets_lost} (at least; {payload} B each); the loss rate predicts "
          f"{expected:.0f} of all {n * packets_per_frame} packets")
    print(f"  leader/trailer only    {stats.get('n_failed_but_all_pixels')} frames (every pixel there, not flagged)")
    print(f"  resend requests        {summary.get('packets_resend_requests')}, packets resent "
          f"{summary.get('packets_resent')} (the fake camera never resends)")
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
