"""Ordinary variations of a tank, through the user's own commands: what the heights and the run say.

Run from the repository root::

    python3 benchmarks/bench_variations.py            # 512^2, about 3 minutes on 2 cores
    python3 benchmarks/bench_variations.py --size 256 # quicker

For each of ``tirdeflect simulate``'s bump and waves (12 bit, 2 frames, 2 DN of
noise) the frames (or the reference) are changed as a tank changes them, then
``tirdeflect process`` and ``tirdeflect compare`` run as a user runs them (the
command line, in a subprocess). Printed per case: the exit status, the
relative RMS height error of each frame (compare's figure) and what the run
said (WARNING and note lines, shortened). A case is fine where its error stays
near the unchanged frames' or the run names what is wrong; the rest is wrong in
silence. The figures of docs/processing.md sections 5 and 10 (6 Dec 2026) come
from this script.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FULL = 4095.0  # 12-bit ceiling


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True)


def _shift(a, rows_px, cols_px):
    """``a`` moved by a sub-pixel amount (cubic): a camera that moved."""
    m = np.float32([[1, 0, cols_px], [0, 1, rows_px]])
    return cv2.warpAffine(a.astype(np.float32), m, a.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT).astype(np.float64)


def _turn(a, deg):
    m = cv2.getRotationMatrix2D((a.shape[1] / 2, a.shape[0] / 2), deg, 1.0)
    return cv2.warpAffine(a.astype(np.float32), m, a.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT).astype(np.float64)


def _zoom(a, scale):
    """The image ``scale`` times as large about the frame's centre (cubic): the lens refocused."""
    m = cv2.getRotationMatrix2D((a.shape[1] / 2 - 0.5, a.shape[0] / 2 - 0.5), 0.0, scale)
    return cv2.warpAffine(a.astype(np.float32), m, a.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT).astype(np.float64)


def _hot(a, rng):
    b = a.copy()
    b.flat[rng.choice(b.size, b.size // 1000, replace=False)] = FULL  # 0.1 %: a camera's ceiling
    return b


def _columns(a):
    return np.arange(a.shape[1])[None, :]


def _bayer(a):
    """A colour camera read raw under white light: its four sub-grids at gains 1 / 0.6 / 0.6 / 0.4."""
    gains = np.ones(a.shape)
    gains[0::2, 1::2], gains[1::2, 0::2], gains[1::2, 1::2] = 0.6, 0.6, 0.4
    return a * gains


def _gamma(a, g=0.6):
    """A camera's gamma (its response a power of the light, as webcams deliver by default)."""
    return FULL * (np.clip(a, 0, None) / FULL) ** g


def _pwm_bands(a, i, period_px=64, depth=0.3):
    """A rolling shutter under PWM-dimmed LEDs: bands of rows 30 % darker, sharp-edged, moving frame to frame."""
    rows = np.arange(a.shape[0])[:, None]
    return a * (1.0 - depth * (np.sin(2 * np.pi * (rows + 17 * i) / period_px) < 0))


def _motion_blur(a, px=5):
    """The pattern smeared ``px`` pixels along the rows' direction (across the columns) in the exposure."""
    return cv2.blur(a.astype(np.float32), (px, 1), borderType=cv2.BORDER_REFLECT).astype(np.float64)


#: name -> (change of the reference or None, change of frame i or None)
VARIATIONS = {
    "as simulated": (None, None),
    "frames 0.7x as bright": (None, lambda a, i, rng: a * 0.7),
    "frames + 300 DN": (None, lambda a, i, rng: a + 300),
    "vignetting 0.8-1.1x": (None, lambda a, i, rng: a * (0.8 + 0.3 * _columns(a) / a.shape[1])),
    "frames 1.6x (clipped)": (None, lambda a, i, rng: a * 1.6),
    "flicker 0.85x / 1.15x": (None, lambda a, i, rng: a * (0.85 if i == 0 else 1.15)),
    "frames 0.15x as bright": (None, lambda a, i, rng: a * 0.15),
    "frames defocused 1 px": (None, lambda a, i, rng: cv2.GaussianBlur(a, (0, 0), 1.0)),
    "0.1 % hot pixels at 4095": (None, lambda a, i, rng: _hot(a, rng)),
    "sharp shadow, half at 0.5x": (None, lambda a, i, rng: a * np.where(_columns(a) < a.shape[1] // 2, 0.5, 1.0)),
    "camera moved 0.5 px": (None, lambda a, i, rng: _shift(a, 0.5, 0.0)),
    "camera turned 0.3 deg": (None, lambda a, i, rng: _turn(a, 0.3)),
    "lens refocused (image 0.2 % larger)": (None, lambda a, i, rng: _zoom(a, 1.002)),
    "reference 1.3x (clipped)": (lambda a: a * 1.3, None),
    "reference defocused 1 px": (lambda a: cv2.GaussianBlur(a, (0, 0), 1.0), None),
    "colour camera read raw (Bayer)": (_bayer, lambda a, i, rng: _bayer(a)),
    "gamma 0.6 (reference and frames)": (_gamma, lambda a, i, rng: _gamma(a)),
    "frames at gamma 1.5, reference linear": (None, lambda a, i, rng: _gamma(a, 1.5)),
    "frames motion-blurred 5 px": (None, lambda a, i, rng: _motion_blur(a)),
    "rolling shutter, PWM light bands": (None, lambda a, i, rng: _pwm_bands(a, i)),
}


def _write(path, a):
    cv2.imwrite(str(path), np.clip(np.rint(a), 0, FULL).astype(np.uint16))


def run_case(sim: Path, work: Path, change_ref, change_frame, extra=(), seed=1):
    rng = np.random.default_rng(seed)
    work.mkdir(parents=True)
    ref = cv2.imread(str(sim / "reference.tif"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    _write(work / "reference.tif", change_ref(ref) if change_ref else ref)
    frames = []
    for i, p in enumerate(sorted(sim.glob("frame_*.tif"))):
        a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64)
        frames.append(work / p.name)
        _write(frames[-1], change_frame(a, i, rng) if change_frame else a)
    out = work / "out.h5"
    p = _cli("process", work / "reference.tif", *frames, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress", *extra)
    c = _cli("compare", out, sim) if out.exists() else None
    errors = [] if c is None else [float(x) for x in re.findall(r"^\s*\d+\s+([\d.]+) %", c.stdout, re.M)]
    said = [re.sub(r"^tirdeflect: ", "", line) for line in p.stderr.splitlines()
            if "WARNING" in line or "note:" in line or "error:" in line]
    return p.returncode, errors, said


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512, help="frame size, px (default 512)")
    ap.add_argument("--width", type=int, default=150, help="characters of each message printed")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="tirdeflect-variations-") as tmp:
        tmp = Path(tmp)
        for surface in ("bump", "waves"):
            sim = tmp / f"sim-{surface}"
            r = _cli("simulate", "--out", sim, "--surface", surface, "--size", args.size, "--frames", 2,
                     "--bits", 12, "--noise", 2)
            if r.returncode:
                print(r.stderr, file=sys.stderr)
                return 1
            print(f"\n{surface}, {args.size}^2, 12 bit: case, exit status, rel. RMS height error of each frame "
                  f"(compare), what the run said")
            cases = list(VARIATIONS.items()) + [("camera moved 0.5 px, --shift-removal",
                                                 (None, VARIATIONS["camera moved 0.5 px"][1], ["--shift-removal"]))]
            for k, (name, spec) in enumerate(cases):
                change_ref, change_frame = spec[0], spec[1]
                extra = spec[2] if len(spec) > 2 else ()
                code, errors, said = run_case(sim, tmp / f"{surface}-{k}", change_ref, change_frame, extra)
                figures = " / ".join(f"{e:.2f} %" for e in errors) or "-"
                print(f"  {name:38s} exit {code}  {figures:18s}")
                for line in said:
                    if "height offset pinned" not in line:
                        print(f"      | {line[:args.width]}")
            shutil.rmtree(sim, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
