"""Ray-traced synthetic data sets with known heights (``tirdeflect simulate``)."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from app.files import h5safe, imageio
from processing.errors import (
    TirdeflectError,
)

from app import version as _version
from app.batch.engine import load_geometry
from app.batch.writer import OutputExistsError, is_same_file, utc_now

__all__ = ["run_simulate", "DEFAULT_SIM_GEOMETRY", "SIM_PATTERN_PERIOD_PX", "SIM_FPS", "SIM_MAX_PHASE_RAD"]

# =========================================================================== simulate


#: Geometry used by `tirdeflect simulate` when no --geometry is given: a typical
#: TIR set-up (notes.md): theta 55 deg, pattern 300 mm below the surface,
#: 0.1 mm per column, telecentric camera, rows running away from the camera.
DEFAULT_SIM_GEOMETRY = {
    "setup": "tir",
    "theta_deg": 55.0,
    "depth_mm": 300.0,
    "pixel_mm": 0.1,
    "rows_toward_camera": False,
}

#: Checkerboard period in columns (x) of the simulated pattern: 20 px, i.e. 2 mm
#: at the default 0.1 mm/px (y period 20 cos(theta) px).
SIM_PATTERN_PERIOD_PX = 20.0
SIM_FPS = 100.0


#: Fewest pixels a simulated board's square may span along either axis (2 per period's half: the
#: board's carriers lie at periods of the square's diagonal, and below this the camera cannot resolve
#: it), and fewest periods across the frame along its coarser axis (the default board's 20 px at the
#: smallest --size, 96 px: 4.8).
SIM_MIN_PERIOD_PX = 4.0
SIM_MIN_PERIODS = 4


def _board_px(period_mm: float, geometry, size_px: int) -> tuple:
    """The board's periods (px) along the image's columns and along its rows (two arrays) at the centre, corners
    and edges of a ``size_px``^2 frame: a camera at a finite distance sees it smaller than ``pixel_mm`` says (its
    rays spread on the way down), and smaller on the far side of the frame than on the near one."""
    at = np.array([0.0, 0.5 * (size_px - 1), size_px - 2.0])
    r, c = (np.repeat(at, 3), np.tile(at, 3))
    px0, py0 = geometry.flat_pattern_point(r, c, (size_px, size_px))
    px1, py1 = geometry.flat_pattern_point(r, c + 1.0, (size_px, size_px))
    px2, py2 = geometry.flat_pattern_point(r + 1.0, c, (size_px, size_px))
    return (period_mm / np.hypot(px1 - px0, py1 - py0),
            period_mm * (geometry.pattern_stretch_y or 1.0) / np.hypot(px2 - px0, py2 - py0))


def _check_period(period_mm: float, geometry, size_px: int) -> None:
    """A clear error where the geometry's ``pattern_period_mm`` cannot be simulated on ``size_px``^2: the board
    too fine or too coarse for the frame, or (a camera at a finite distance) its period changing across the
    frame more than the carrier search takes in one peak."""
    from processing import forward
    from processing.carriers import find_carriers
    from processing.errors import NoCarrierError

    along = _board_px(period_mm, geometry, size_px)
    finest, coarsest = float(min(a.min() for a in along)), float(max(a.max() for a in along))
    board = (f"pattern_period_mm = {period_mm:g}" if geometry.pattern_period_mm else
             f"the default board ({SIM_PATTERN_PERIOD_PX:g} px at pixel_mm, {period_mm:g} mm)")
    key = "camera_distance_mm" if geometry.setup == "tir" else "fsss_camera_distance_mm"
    distance = getattr(geometry, key)
    seen = "" if distance is None else f" and a camera {distance:g} mm away, which sees the board smaller"
    if finest < SIM_MIN_PERIOD_PX:
        raise TirdeflectError(
            f"{board} is {finest:.1f} px along the image's finer axis at pixel_mm = {geometry.pixel_mm:g}{seen}: "
            f"below {SIM_MIN_PERIOD_PX:g} px the camera cannot resolve the board; give a longer period (at least "
            f"{SIM_MIN_PERIOD_PX * period_mm / finest:.3g} mm as pattern_period_mm)"
            + (" or a more distant camera" if distance is not None else ""))
    if coarsest * SIM_MIN_PERIODS > size_px:
        raise TirdeflectError(
            f"{board} is {coarsest:.1f} px: a {size_px} px frame holds fewer than "
            f"{SIM_MIN_PERIODS} periods, too few for the carrier search; give a shorter period or a larger --size")
    if distance is None:
        return
    pattern = forward.Checkerboard(period_mm=period_mm, edge_softness_mm=geometry.pixel_mm,
                                   stretch_y=geometry.pattern_stretch_y or 1.0)
    flat, _ = forward.render(forward.FlatSurface(), geometry, (size_px, size_px), pattern, supersample=1)
    try:
        find_carriers(np.asarray(flat, np.float32))
    except NoCarrierError:
        axis = int(np.argmax([a.max() / a.min() for a in along]))
        raise TirdeflectError(
            f"a camera {distance:g} mm away sees {board} at {along[axis].min():.1f} to {along[axis].max():.1f} px "
            f"along the image's {('columns', 'rows')[axis]} across the frame (perspective), a spread the carrier "
            f"search cannot take as one peak; give a more distant camera ({key}), a longer period or a smaller "
            f"--size") from None


#: Rays a simulated frame traces per carrier period of its board, along each axis, at least
#: (:func:`rays_per_pixel`). Measured (by-hand sweep, 7 Dec 2026, 256^2, a 2 um bump, the default
#: board seen by a TIR camera at 1500 mm: carriers 4.43 px): 2 x 2 rays a pixel (8.9 a period) put the
#: frame's heights 0.59 % off the truth, 4 x 4 (17.7) 0.15 %, 6 x 6 0.14 %; at 400-800 mm the sweep saw
#: 2.3-3.1 % with 2 x 2 rays and 0.19 % with 6 x 6. The default telecentric board (carriers 9.95 px)
#: keeps its 2 x 2.
SIM_RAYS_PER_PERIOD = 16.0
#: Most rays per pixel and axis simulate traces (its time grows with their square).
SIM_MAX_RAYS = 8


def rays_per_pixel(geometry, size_px: int, pattern) -> int:
    """Rays per pixel and axis for a simulated frame: 2, or as many as give the board's shortest carrier
    period :data:`SIM_RAYS_PER_PERIOD` rays (a camera at a finite distance sees the board smaller, and
    2 x 2 rays a pixel made the frames, not the processing, percent off the truth), at most
    :data:`SIM_MAX_RAYS`; the carriers measured on the flat frame traced with one ray a pixel."""
    from processing import forward
    from processing.carriers import find_carriers
    from processing.errors import NoCarrierError

    flat, _ = forward.render(forward.FlatSurface(), geometry, (size_px, size_px), pattern, supersample=1)
    try:
        shortest = float(np.min(find_carriers(np.asarray(flat, np.float32)).periods_px))
    except NoCarrierError:
        return 2
    return int(min(SIM_MAX_RAYS, max(2, math.ceil(SIM_RAYS_PER_PERIOD / shortest))))


#: Largest carrier phase |k . u| (rad) each --surface is scaled to reach (on any
#: geometry): below pi for all but deep-dimple, which needs unwrapping, as the
#: notes.md example (15 um deep at H = 300 mm, theta = 55 deg) does.
SIM_MAX_PHASE_RAD = {"bump": 2.3, "dimple": 2.3, "waves": 2.6, "deep-dimple": 5.0}


def _sim_scene(name: str, geometry, size: int, n_frames: int, seed: int, amplitude: float = 1.0):
    """Surface (or scene with ``at(t_s)``) for a --surface name.

    Features scale with the field (``size * pixel_mm``); heights are the
    nominal ones below times ``amplitude`` (:func:`_sim_amplitude` picks it so
    the largest carrier phase is :data:`SIM_MAX_PHASE_RAD`). Nominal, at
    512 px: bump 4 um, sigma 1/8 of the field; dimple deepening over the frames
    to 4 um; deep-dimple 15 um, sigma field/4.65; waves 0.7 um RMS, six
    travelling waves of 1/4 to 1/2 the field. Heights in mm, positions in the
    image frame (mm from the image centre).
    """
    from processing import forward

    fov_mm = size * geometry.pixel_mm  # field width along x
    scale = size / 512.0 * amplitude
    if name == "bump":
        return forward.GaussianBump(amplitude_mm=0.004 * scale, sigma_mm=fov_mm / 8.0)
    if name == "dimple":
        # a dimple that deepens over the frames (a disc approaching the surface)
        depth_mm, sigma_mm = 0.004 * scale, fov_mm / 8.0

        def at(t_s: float):
            i = int(round(t_s * SIM_FPS))
            return forward.Dimple((i + 1) / n_frames * depth_mm, sigma_mm)

        return at
    if name == "deep-dimple":
        return forward.Dimple(0.015 * scale, fov_mm / 4.65)
    if name == "waves":
        field = forward.WaveField.random(
            6, amplitude_rms_mm=0.0007 * scale, wavelength_range_mm=(fov_mm / 4.0, fov_mm / 2.0),
            seed=seed)
        return forward.TravellingWaves(field.components)
    raise TirdeflectError(f"unknown --surface {name!r}; choose bump, dimple, waves or deep-dimple")


def _surface_at(scene, t_s: float):
    from processing import forward

    if isinstance(scene, forward.Surface):
        return scene
    return scene.at(t_s) if hasattr(scene, "at") else scene(t_s)


def _sim_amplitude(name, geometry, size, n_frames, seed, pattern, target_rad) -> tuple:
    """Amplitude factor making the largest carrier phase ``target_rad``.

    The phase is ``|k_s . u|`` with ``u`` the exact displacement (ray traced,
    on a 64 x 64 subgrid) and ``k_s`` the carriers found on the rendered flat
    reference; it is evaluated at the first and last frame times (phase is
    linear in amplitude while rays do not cross). Returns (factor, phase at
    factor 1).
    """
    from processing import forward
    from processing.carriers import find_carriers

    shape = (size, size)
    flat, _ = forward.render(forward.FlatSurface(), geometry, shape, pattern)
    k = find_carriers(flat).wavevectors  # (2, 2) rad/px, (row, col)
    sub = np.linspace(0, size - 1, min(size, 64))
    scene = _sim_scene(name, geometry, size, n_frames, seed)
    phase = 0.0
    for t_s in {0.0, (n_frames - 1) / SIM_FPS}:
        u, _ = forward.true_displacement(_surface_at(scene, t_s), geometry, shape,
                                         rows_px=sub, cols_px=sub)
        phase = max(phase, float(np.nanmax(np.abs(np.tensordot(k, u, axes=([1], [0]))))))
    if not phase > 0:
        raise TirdeflectError(f"--surface {name} moves no pattern point in this geometry; "
                              f"check --geometry")
    return target_rad / phase, phase


def run_simulate(args) -> None:
    """Write a simulated data set to ``args.out`` (the ``simulate`` subcommand's namespace;
    errors raise :class:`TirdeflectError`)."""
    from processing import Geometry, forward

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise TirdeflectError(f"--out {str(out)!r} exists and is not a directory; choose a directory")
    if out.is_dir() and any(out.glob("reference.*")) and not args.overwrite:
        raise OutputExistsError(
            f"{str(out)!r} already holds a simulated data set; choose another --out or add --overwrite"
        )
    _check_outputs_are_not_inputs(out, args.geometry)
    # before the ray tracing: a folder where nothing can be created failed only at the end
    h5safe.check_creatable(out / "heights.h5", "choose another --out (a folder you can write to)")
    if not math.isfinite(args.noise) or args.noise < 0:
        raise TirdeflectError(f"--noise must be a finite RMS >= 0 grey levels; got {args.noise}")
    if args.size < 96:
        raise TirdeflectError(f"--size must be at least 96 px (about ten pattern periods, what the "
                              f"carrier search needs); got {args.size}")
    if args.geometry:
        geometry = load_geometry(args.geometry)
    else:
        geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    if getattr(geometry, "pattern", None) == "dots":
        raise TirdeflectError(
            f"{args.geometry}: pattern = \"dots\": simulate renders a checkerboard only (its heights are scaled "
            f"by the board's carrier phase), and would write a geometry naming dots beside it; remove the "
            f"pattern key (random dots are checked by benchmarks/bench_processing.py's dots table)")
    # the board the geometry describes (its pattern_period_mm, else 20 px; stretched along y where it
    # says so), and the geometry written beside the frames names its period, so that it is checked
    period_mm = geometry.pattern_period_mm or SIM_PATTERN_PERIOD_PX * geometry.pixel_mm
    _check_period(period_mm, geometry, args.size)
    pattern = forward.Checkerboard(period_mm=period_mm, edge_softness_mm=geometry.pixel_mm,
                                   stretch_y=geometry.pattern_stretch_y or 1.0)
    geometry = dataclasses.replace(geometry, pattern_period_mm=pattern.period_mm)
    target = SIM_MAX_PHASE_RAD[args.surface] if args.max_phase is None else args.max_phase
    if not (math.isfinite(target) and target > 0):
        raise TirdeflectError(f"--max-phase must be a positive number of radians; got {target}")
    factor, _ = _sim_amplitude(args.surface, geometry, args.size, args.frames, args.seed,
                               pattern, target)
    scene = _sim_scene(args.surface, geometry, args.size, args.frames, args.seed, factor)
    sim = forward.simulate(
        scene, geometry, (args.size, args.size), args.frames, pattern=pattern, fps=SIM_FPS,
        bits=args.bits, noise_rms=args.noise, seed=args.seed,
        supersample=rays_per_pixel(geometry, args.size, pattern),
    )
    args.max_phase = target
    out.mkdir(parents=True, exist_ok=True)
    # Write into a temporary directory inside DIR and move the files into place
    # only when all are written: a failure (disk full, Ctrl-C) leaves an earlier
    # data set in DIR as it was.
    tmp = Path(tempfile.mkdtemp(prefix=".simulate-", dir=out))
    try:
        n_frames, hmax_um = _write_simulation(tmp, sim, geometry, args)
        stale = [p for p in out.iterdir() if _SIM_FILE.fullmatch(p.name)]
        written = {p.name for p in tmp.iterdir()}
        for item in sorted(tmp.iterdir()):
            os.replace(item, out / item.name)
        for old in stale:  # frames of an earlier, longer data set: not part of this one
            if old.name not in written:
                old.unlink()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"tirdeflect: wrote reference, {n_frames} frame(s) ({args.bits} bit), heights.h5 "
          f"(max |h| {hmax_um:.2f} um) and geometry.toml to {out}", file=sys.stderr)


#: the files of a simulated data set (what --overwrite replaces)
_SIM_FILE = re.compile(r"(reference|frame_\d{4,})\.(png|tif)|geometry\.toml|heights\.h5")


def _check_outputs_are_not_inputs(out: Path, geometry_path) -> None:
    """Refuse a DIR whose data-set files include the --geometry file given."""
    if geometry_path is None or not out.is_dir():
        return
    for p in out.iterdir():
        if _SIM_FILE.fullmatch(p.name) and is_same_file(p, geometry_path):
            raise TirdeflectError(
                f"--geometry {str(geometry_path)!r} is {str(p)!r}, a file of the data set that "
                f"simulate writes into --out {str(out)!r}; copy the geometry elsewhere or choose "
                f"another --out: tirdeflect never writes over its inputs")


def _write_simulation(out: Path, sim, geometry, args) -> tuple:
    import h5py

    suffix = ".png" if args.bits <= 8 else ".tif"
    imageio.write_image(out / f"reference{suffix}", sim.reference)
    names = []
    for k, frame in enumerate(sim.frames):
        name = f"frame_{k:04d}{suffix}"
        imageio.write_image(out / name, frame)
        names.append(name)
    geometry_text = geometry.to_toml_text()
    (out / "geometry.toml").write_text(geometry_text, encoding="utf-8")
    heights = np.asarray(sim.heights_mm, dtype=np.float32)
    with h5py.File(out / "heights.h5", "w") as f:
        ds = f.create_dataset("height", data=heights, chunks=(1, *heights.shape[1:]))
        ds.attrs["units"] = "mm"
        ds.attrs["description"] = (
            "true surface height sampled where each pixel's camera ray meets the surface")
        lost = f.create_dataset("lost", data=np.asarray(sim.lost, dtype=np.uint8),
                                chunks=(1, *heights.shape[1:]))
        lost.attrs["description"] = "1 where TIR is lost or rays cross (unmeasurable)"
        f.create_dataset("time_s", data=np.asarray(sim.times_s, dtype=np.float64))
        f.create_dataset("frame_file", data=np.array(names, dtype=object),
                         dtype=h5py.string_dtype())
        f.attrs["surface"] = args.surface
        f.attrs["max_phase_rad"] = args.max_phase
        f.attrs["bits"] = args.bits
        f.attrs["noise_rms"] = args.noise
        f.attrs["seed"] = args.seed
        f.attrs["pattern_period_mm"] = geometry.pattern_period_mm
        f.attrs["geometry_toml"] = geometry_text
        f.attrs["software_version"] = _version()
        f.attrs["created_utc"] = utc_now()
    return len(names), float(np.max(np.abs(heights))) * 1e3

