"""Carrier wavevectors of a checkerboard image, and pattern checks.

The reference's carriers (:class:`Carriers`, :func:`find_carriers`) are
computed in :mod:`processing.carrier_peaks` and re-exported here; this module
adds the carriers of distorted frames (:func:`find_carriers_local`,
:func:`find_carriers_live`) and the pattern checks (:func:`check_pattern_match`,
:func:`match_error`).

The method (the two diagonal peaks, sub-bin precision, theta from the aspect
of a square pattern) is described in :mod:`processing.carrier_peaks`.  The
checks here refuse frames whose pattern differs from the reference's
(:class:`~processing.errors.PatternMismatchError`) or that show none
(:class:`~processing.errors.NoCarrierError`), and a reference whose board
disagrees with the geometry's ``pattern_period_mm``
(:func:`check_board_period`).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
import scipy.fft

from .carrier_peaks import (ISOLATION_RING_BINS, ISOLATION_RING_DC, ISOLATION_RING_DR, MIN_ISOLATION,  # noqa: F401
                            MIN_PEAK_CONTRAST, Carriers, as_float_image, display_spectrum, find_carriers,
                            frame_spectrum, hann, rotation_from_carriers, theta_from_carriers, windowed_spectrum)
from .errors import GeometryError, NoCarrierError, PatternMismatchError
from .half_spectrum import display_bins

__all__ = [
    "Carriers",
    "find_carriers",
    "find_carriers_local",
    "find_carriers_live",
    "find_reference_carriers",
    "tile_origins",
    "hann",
    "check_pattern_match",
    "check_board_period", "board_period_note", "keystone_note",
    "board_period_check",
    "BoardPeriodCheck",
    "BOARD_PERIOD_TOLERANCE", "BOARD_PERIOD_NOTE", "ROOT_TWO_BAND",
    "match_error",
    "theta_from_carriers",
    "rotation_from_carriers",
    "display_bins", "display_spectrum",
    "frame_spectrum", "windowed_spectrum",
]


def tile_origins(shape, tile_px: int, max_tiles: int = 64) -> tuple:
    """Top-left corners of :func:`find_carriers_local`'s tiles: ``(row_origins, col_origins)``.

    At most about ``max_tiles`` tiles of side ``tile_px``, spread evenly over
    an image of ``shape`` (overlapping by half where the image holds few).
    """
    rows, cols = shape
    n_r, n_c = rows // tile_px, cols // tile_px
    per_axis = max(1, int(math.sqrt(max_tiles)))
    r0s = np.linspace(0, rows - tile_px, min(per_axis, max(n_r, 1) * 2 - 1 if n_r > 1 else 1)).astype(int)
    c0s = np.linspace(0, cols - tile_px, min(per_axis, max(n_c, 1) * 2 - 1 if n_c > 1 else 1)).astype(int)
    return np.unique(r0s), np.unique(c0s)


def find_carriers_local(image, *, tile_px: int | None = None, max_tiles: int = 64,
                        min_fraction: float = 1.0 / 3.0, **options) -> Carriers:
    """Carriers of an image whose pattern is distorted: median of local carriers in tiles.

    A disturbed surface (waves, a dimple) shifts the pattern by a few pixels
    that vary across the image: the carrier's phase is modulated, and its
    peak in the whole image's spectrum spreads into sidebands a few bins on
    either side (phase modulation of index ``2 pi |u| / period``: about 3 rad
    for 3 px on a 6-px pattern). :func:`find_carriers` then sees no isolated
    peak ("a streak or smear") although the pattern is plainly there. Over a
    tile a few periods wide the distortion is nearly a uniform shift, so each
    tile shows a compact peak at its *local* carrier; the median over tiles
    is the undisturbed carrier (waves average out), to about 0.1 % in period
    and 0.1 deg in theta on the synthetic tank's waves.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
    tile_px : int, optional
        Tile side; default: tiles of 64 px, or 128 px when 64-px tiles find
        no carriers (periods above 16 px).
    max_tiles : int
        At most about this many tiles, spread evenly over the image (speed).
    min_fraction : float
        Carriers must be found in at least this fraction of the tiles.
    **options
        Passed on to :func:`find_carriers` for each tile.

    Returns
    -------
    Carriers
        ``freq``: component-wise median of the tiles' carriers; ``contrast``,
        ``sharpness``: medians over the tiles (sharpness of a tile's peak, 0..1).

    Raises
    ------
    NoCarrierError
        If too few tiles show a checkerboard.
    """
    img = as_float_image(image, "image")
    rows, cols = img.shape
    sizes = [int(tile_px)] if tile_px else [s for s in (64, 128) if s <= min(rows, cols)]
    if not sizes:
        raise NoCarrierError(f"image {rows} x {cols} is too small for local carriers (tiles of 64 px)")
    found = (0, 0)
    for size in sizes:
        r0s, c0s = tile_origins((rows, cols), size, max_tiles)
        freqs, contrasts, sharps = [], [], []
        for r0 in r0s:
            for c0 in c0s:
                try:
                    c = find_carriers(img[r0:r0 + size, c0:c0 + size], **options)
                except NoCarrierError:
                    continue
                freqs.append(c.freq)
                contrasts.append(c.contrast)
                sharps.append(c.sharpness)
        n_tiles = len(r0s) * len(c0s)
        if freqs and len(freqs) >= min_fraction * n_tiles:
            return Carriers(freq=np.median(np.array(freqs), axis=0), shape=(rows, cols),
                            contrast=np.median(np.array(contrasts), axis=0),
                            sharpness=np.median(np.array(sharps), axis=0))
        found = max(found, (len(freqs), n_tiles))
    raise NoCarrierError(
        f"no checkerboard in enough parts of the image (carriers found in {found[0]} of {found[1]} tiles, "
        f"need {min_fraction:.0%}): check that the checkerboard is in focus, lit and fills the view")


def find_carriers_live(image) -> tuple:
    """Carriers of a live frame for alignment: ``(Carriers, disturbed)``.

    The whole image's peaks first (:func:`find_carriers`, most precise); when
    they are smeared by a disturbed surface, the median of local carriers
    (:func:`find_carriers_local`) and ``disturbed=True``: the numbers are
    right, but a reference taken now would not be of still water.
    (:func:`processing.alignment.carriers_without_reference` gives the same
    numbers faster, the tiles searched together: the Alignment tab's.)

    Raises
    ------
    NoCarrierError
        The whole image's message, if neither finds a checkerboard.
    """
    try:
        return find_carriers(image), False
    except NoCarrierError as whole:
        try:
            return find_carriers_local(image), True
        except NoCarrierError:
            raise whole from None


def find_reference_carriers(reference) -> Carriers:
    """The reference's carriers (:func:`find_carriers`), refusing a reference of moving water.

    Where the whole image shows no clear peak but local tiles do
    (:func:`find_carriers_live` says ``disturbed``), the checkerboard is
    there, distorted: the surface moved while the reference was taken, and
    every height would be measured against that surface.

    Raises
    ------
    NoCarrierError
        Saying so and what to do; or :func:`find_carriers`' own message where
        no checkerboard is seen at all, with the same advice (waves strong
        enough smear the local patches' peaks too).
    """
    try:
        carriers, disturbed = find_carriers_live(reference)
    except NoCarrierError as exc:
        raise NoCarrierError(f"{exc}; if the water was moving when the reference was taken, take it again on "
                             "still water; if the pattern is random dots, say so: pattern = \"dots\" in the "
                             "geometry (tirdeflect process --pattern dots)") from None
    if disturbed:
        raise NoCarrierError(
            f"the reference shows the checkerboard distorted (periods {carriers.periods_px[0]:.1f} and "
            f"{carriers.periods_px[1]:.1f} px in local patches, no clear peak over the whole image): the water "
            "surface was moving when it was taken; take the reference again on still water (the Alignment tab "
            "says when the surface has settled). A still surface seen this distorted needs a flatter view of "
            "the board: a longer lens, a farther camera")
    return carriers


def match_error(expected: Carriers, measured_freq) -> tuple:
    """Largest relative period error and rotation error (deg) between carriers.

    ``measured_freq`` (2, 2) is matched carrier by carrier, up to sign.
    """
    changes = _carrier_changes(expected, measured_freq)
    return max(abs(ratio - 1.0) for ratio, _ in changes), max(abs(d) for _, d in changes)


def _carrier_changes(expected: Carriers, measured_freq) -> list:
    """Per carrier, ``(frequency ratio measured / expected, direction change deg)``, matched up to sign."""
    out = []
    for s in range(2):
        e = np.asarray(expected.freq[s])
        m = np.asarray(measured_freq[s])
        if np.dot(e, m) < 0:
            m = -m
        out.append((float(np.hypot(*m) / np.hypot(*e)),
                    math.degrees(math.atan2(e[0] * m[1] - e[1] * m[0], float(np.dot(e, m))))))
    return out


#: A frame whose own carrier search fails (peaks smeared by strong deformation,
#: or no pattern) is judged by where its spectral power lies: at least this
#: fraction of it (within the carrier band) must sit within
#: :data:`SMEARED_RADIUS` x the carriers' spacing of the reference's carriers,
#: and the power-weighted centroid of that power (the frame's mean carrier: a
#: phase modulation moves it only by its mean gradient over the field) may
#: differ from the reference's carrier by at most :data:`SMEARED_PERIOD_TOL`
#: in period and :data:`SMEARED_ROTATION_TOL_DEG` in direction.  Measured on
#: the frames of shared/data whose peaks are smeared (frame 211 of prueba1,
#: the floater 0_5mm_circular) and the 15 um deep dimple of the tests: their
#: own reference gives fractions 0.66-0.83 and centroids 1.7-2.3 % off; a
#: reference of another pattern gives 0.002-0.77 and 12.5-17.3 % off.
SMEARED_MIN_FRACTION = 0.45
SMEARED_RADIUS = 0.25
SMEARED_PERIOD_TOL = 0.08
SMEARED_ROTATION_TOL_DEG = 6.0
#: A smoothed spectral peak standing this many times (power) above the median
#: power at its radius is a pattern; below it the frame shows no pattern.
SMEARED_MIN_CONTRAST = 25.0
#: Fraction of each image side tapered by the window of that check.
SMEARED_TAPER = 0.25


#: Largest difference between the board period a reference's carriers show through the geometry and the
#: geometry's ``pattern_period_mm``, as ``max(r, 1 / r) - 1`` of their ratio ``r`` (the same either way:
#: :func:`check_board_period`). The measure is exact on ray-traced references (telecentric and pinhole,
#: turned and stretched boards: 1.2000 mm for 1.2); a theta_deg 2 deg off moves it 2.5-4.0 % (measured, 256^2,
#: telecentric to a camera at 1500 mm), which passes (heights hardly depend on it), and a pixel_mm 5 % off
#: either way (5.0 % high, 5.3 % low), which moves every height by about 10 %, is refused (until 7 Dec 2026
#: the bound was 5 % on ``r - 1``: pixel_mm 4.5-5 % high passed silently, 9-10 % off).
BOARD_PERIOD_TOLERANCE = 0.045
#: From this difference up to :data:`BOARD_PERIOD_TOLERANCE` the run goes on with a note naming it and what it
#: means for the heights (a theta_deg 1 deg off moves it 1.3-1.9 %, below).
BOARD_PERIOD_NOTE = 0.02
#: The hint that crossed lines or cosines are described as a checkerboard (or the reverse: periods sqrt(2)
#: apart) is given within this of sqrt(2) only: the measure is exact where the rest of the geometry is right,
#: and a theta_deg 1 deg off moves it by 2 % at most; a camera 1500 mm away declared telecentric puts the
#: period 1.349 times off, 4.8 % from sqrt(2), which a 5 % band called a sqrt(2) (by-hand trial of 7 Dec 2026).
ROOT_TWO_BAND = 0.02


class BoardPeriodCheck(NamedTuple):
    """The board period seen through the scale against the printed one (:func:`board_period_check`)."""

    #: Period the carriers show through the geometry, mm (NaN: not measurable there).
    period_mm: float
    #: ``geometry.pattern_period_mm`` (None: not given, nothing judged).
    printed_mm: Optional[float]
    #: ``period_mm / printed_mm - 1`` (NaN without a printed period).
    off: float
    #: The ``pixel_mm`` that makes them agree (the period seen scales with it).
    implied_pixel_mm: float
    #: ``apart`` above :data:`BOARD_PERIOD_TOLERANCE`.
    wrong: bool
    #: ``max(r, 1 / r) - 1`` of ``r = period_mm / printed_mm``: the difference, the same either way.
    apart: float = math.nan
    #: ``apart`` from :data:`BOARD_PERIOD_NOTE` up to the tolerance: named, not refused.
    noted: bool = False


def board_period_check(geometry, period_mm: float) -> BoardPeriodCheck:
    """Judge ``period_mm`` (:meth:`processing.geometry.Geometry.board_period_mm`) against the
    geometry's ``pattern_period_mm``: the one judgement of the reference's check
    (:func:`check_board_period`) and of the Alignment tab."""
    printed = geometry.pattern_period_mm
    if printed is None:
        return BoardPeriodCheck(period_mm, None, math.nan, math.nan, False)
    ratio = period_mm / printed
    apart = max(ratio, 1.0 / ratio) - 1.0 if ratio > 0 else math.nan
    # NaN (a camera check_frame refuses, with its own reason) is not judged wrong
    return BoardPeriodCheck(period_mm, printed, ratio - 1.0, geometry.pixel_mm * printed / period_mm,
                            bool(apart > BOARD_PERIOD_TOLERANCE), apart,
                            bool(BOARD_PERIOD_NOTE <= apart <= BOARD_PERIOD_TOLERANCE))


def check_board_period(geometry, carriers: Carriers, frame_shape, reference=None) -> str:
    """Refuse a reference whose checkerboard is not the geometry's; return a note (or "") where the board is a
    little off or, given the ``reference`` image, where its perspective is not the declared camera's:
    :func:`keystone_note` and :func:`board_period_note`, joined.

    Raises
    ------
    GeometryError
        As :func:`board_period_note`.
    """
    period = board_period_note(geometry, carriers, frame_shape, reference)  # (refuses first)
    keystone = "" if reference is None else keystone_note(geometry, carriers, frame_shape, reference)
    return "; ".join(n for n in (keystone, period) if n)


def _keystone(geometry, reference, carriers: Carriers):
    """:func:`processing.keystone.keystone_check` of a TIR reference; None for FS-SS, which looks straight down
    (no key makes a keystone, nothing to judge)."""
    from .keystone import keystone_check

    return keystone_check(geometry, reference, carriers) if geometry.setup == "tir" else None


def keystone_note(geometry, carriers: Carriers, frame_shape, reference) -> str:
    """The note on a ``reference`` whose keystone is not the declared camera's
    (:func:`processing.keystone.keystone_check`), "" where it is: a note, not a refusal, for a water surface
    that was not flat when the reference was taken (frames averaged over waves: the board 1.9 % shorter in the
    bottom third, read as a camera 3565 mm away) changes the board's period across the image as a camera
    does.  0.02-0.12 s a reference (256^2-1024^2): only where the note is said, not in every chain built."""
    from .board_scale import keystone_message

    keystone = _keystone(geometry, reference, carriers)
    if keystone is None or not keystone.wrong:
        return ""
    return keystone_message(geometry, keystone, carriers.freq, frame_shape)


def board_period_note(geometry, carriers: Carriers, frame_shape, reference=None) -> str:
    """Refuse a reference whose checkerboard is not the geometry's; return a note (or "") where the board is a
    little off.

    Where ``geometry.pattern_period_mm`` is given, the period that the
    reference's ``carriers`` show through ``pixel_mm``, ``theta_deg`` and the
    camera distance (:meth:`processing.geometry.Geometry.board_period_mm`)
    must agree with it within :data:`BOARD_PERIOD_TOLERANCE`
    (:func:`board_period_check`): heights scale with ``pixel_mm`` squared,
    and nothing else in a frame tells a wrong ``pixel_mm`` apart; from
    :data:`BOARD_PERIOD_NOTE` up to it, a note says so.

    Raises
    ------
    GeometryError
        Naming both periods, the keys that set the board's scale in the image
        (:func:`processing.board_scale.scale_keys`), the value of each that
        would agree, and, given the ``reference`` image, what its keystone shows.
    """
    from .board_scale import scale_alternatives, scale_keys

    if geometry.pattern_period_mm is None:
        return _cell_shape_note(geometry, carriers, frame_shape)
    c = board_period_check(geometry, geometry.board_period_mm(carriers.freq, frame_shape))
    if c.wrong:
        keystone = None if reference is None else _keystone(geometry, reference, carriers)
        _refuse_board(geometry, carriers, frame_shape, c, scale_keys(geometry) + ". " + scale_alternatives(
            geometry, carriers.freq, frame_shape, c.printed_mm, c.implied_pixel_mm, keystone))
    return _board_note(geometry, c) if c.noted else ""


def _board_note(geometry, c) -> str:
    """The note of a board :data:`BOARD_PERIOD_NOTE` to :data:`BOARD_PERIOD_TOLERANCE` off the geometry's."""
    from .board_scale import heights_off_pct, scale_keys

    return (f"the reference's checkerboard has a period of {c.period_mm:.4g} mm through this geometry, "
            f"pattern_period_mm = {c.printed_mm:g}: {100 * c.apart:.1f} % apart (refused above "
            f"{100 * BOARD_PERIOD_TOLERANCE:.1f} %). If pixel_mm is what is off, every height is about "
            f"{heights_off_pct(1.0 + c.off):.0f} % off (heights scale with it squared)"
            + ("; a theta_deg 1-2 deg off moves the period that much with little effect on heights"
               if geometry.setup == "tir" else "") + f". The board's scale is set by {scale_keys(geometry)}")


def _refuse_board(geometry, carriers: Carriers, frame_shape, c: BoardPeriodCheck, keys: str) -> None:
    """Raise the period check's refusal (or its cells' shape's, where that is what is off)."""
    from .board_scale import heights_off_pct, root_two_hint, setup_words

    aspect, stretch = geometry.board_cell_aspect(carriers.freq, frame_shape), float(geometry.pattern_stretch_y or 1.0)
    if math.isfinite(aspect) and abs(aspect / stretch - 1.0) > BOARD_ASPECT_TOLERANCE:
        raise GeometryError(_aspect_message(geometry, carriers, aspect, stretch, setup_words(geometry)))
    raise GeometryError(
        f"the reference's checkerboard has a period of {c.period_mm:.4g} mm through this geometry "
        f"({setup_words(geometry)}), but pattern_period_mm = {c.printed_mm:g}: {100 * c.apart:.0f} % "
        f"apart (more than {100 * BOARD_PERIOD_TOLERANCE:.1f} %). Heights scale with the board's scale in the image "
        f"squared: with pixel_mm the one off, they would be about {heights_off_pct(1.0 + c.off):.0f} % off. The "
        f"board's scale in the image is set by {keys}" + root_two_hint(c.period_mm, c.printed_mm, ROOT_TWO_BAND))


#: Where the period check fails and the board's cells look more than this much longer or shorter along y
#: than ``pattern_stretch_y`` says (:meth:`processing.geometry.Geometry.board_cell_aspect`), the cause named is
#: the board's shape or theta, not pixel_mm: by-hand trial of 7 Dec 2026, a stretched board not declared was
#: told "pixel_mm should be 0.08152", and with that pixel_mm every height was 34 % off, exit 0. (A theta_deg
#: 2 deg off moves the aspect by about 5 % at 55 deg; the period check itself allows that.)
BOARD_ASPECT_TOLERANCE = 0.10


def _aspect_message(geometry, carriers: Carriers, aspect: float, stretch: float, setup: str) -> str:
    """The refusal of a reference whose board's cells are not of the shape ``pattern_stretch_y`` says."""
    from .board_scale import cell_shape_words

    return (cell_shape_words(aspect, stretch, setup, _carriers_theta(geometry, carriers, stretch))
            + "; pixel_mm is not judged until the board's shape agrees")


def _carriers_theta(geometry, carriers: Carriers, stretch: float) -> float:
    """The theta a board of cells ``stretch`` long along y implies (NaN where it cannot be told: FS-SS, a
    finite camera)."""
    if geometry.setup == "tir" and geometry.camera_distance_mm is None:
        return theta_from_carriers(carriers.freq, stretch)
    return math.nan


def _cell_shape_note(geometry, carriers: Carriers, frame_shape) -> str:
    """Without ``pattern_period_mm``: the note on a board whose cells are not of the declared shape, more than
    :data:`BOARD_ASPECT_TOLERANCE` (a note, not a refusal: a board printed so, which `tirdeflect pattern
    --suggest` proposes, gives right heights; a wrong theta_deg or an image stretched along one axis does not:
    1.3x along x, 31-40 % off with exit 0 and no word, by-hand trial of 7 Dec 2026)."""
    from .board_scale import cell_shape_words, setup_words

    aspect, stretch = geometry.board_cell_aspect(carriers.freq, frame_shape), float(geometry.pattern_stretch_y or 1.0)
    if not math.isfinite(aspect) or abs(aspect / stretch - 1.0) <= BOARD_ASPECT_TOLERANCE:
        return ""
    return (cell_shape_words(aspect, stretch, setup_words(geometry), _carriers_theta(geometry, carriers, stretch))
            + "; or the image is stretched along one axis (pixels not square). Heights are right in the first "
            "case only")


def check_pattern_match(carriers: Carriers, frame, *, period_tol: float = 0.04,
                        rotation_tol_deg: float = 3.0) -> Carriers:
    """Check that a frame shows the reference's pattern (same periods and rotation).

    The check always decides: a frame passes, is refused as another pattern,
    or is refused as showing no pattern at all.

    Parameters
    ----------
    carriers : Carriers
        From :func:`find_carriers` on the reference.
    frame : ndarray, shape (rows, cols)
        Camera frame.
    period_tol : float, optional
        Largest accepted relative period difference of either carrier.
    rotation_tol_deg : float, optional
        Largest accepted carrier direction difference, degrees.

    Returns
    -------
    Carriers
        The frame's carriers.  When the frame shows no compact carrier peaks
        (a strongly deformed frame smears them), the power-weighted centroids
        of its spectrum around the reference's carriers (``contrast`` and
        ``sharpness`` NaN); see :data:`SMEARED_MIN_FRACTION`.

    Raises
    ------
    PatternMismatchError
        Naming the measured and expected periods and rotation.
    NoCarrierError
        The frame shows no pattern at all (uniform, black, noise, blurred):
        nothing in it can be measured.
    """
    try:
        found = find_carriers(frame)
    except NoCarrierError as exc:
        return _check_smeared(carriers, frame, exc)
    # The frame's two peaks may come in the other order.
    rel_a, ang_a = match_error(carriers, found.freq)
    rel_b, ang_b = match_error(carriers, found.freq[::-1])
    in_order = max(rel_a, ang_a / 90) <= max(rel_b, ang_b / 90)
    rel, ang = (rel_a, ang_a) if in_order else (rel_b, ang_b)
    if rel > period_tol or ang > rotation_tol_deg:
        raise PatternMismatchError(
            f"the frame's pattern does not match the reference: measured {found.describe()}; "
            f"expected {carriers.describe()} (periods differ by {100 * rel:.1f} %, carrier "
            f"directions by {ang:.1f} deg; tolerance {100 * period_tol:.0f} % and "
            f"{rotation_tol_deg:.0f} deg). Record a new reference for this pattern, "
            "camera position and zoom" + _zoom_words(carriers, found.freq if in_order else found.freq[::-1],
                                                    rotation_tol_deg))
    return found


def _zoom_words(expected: Carriers, measured_freq, rotation_tol_deg: float) -> str:
    """The words a refused frame gets where its two carriers kept their directions (within ``rotation_tol_deg``)
    and changed their periods alike (a zoom, or a stretch along the rows or columns, which changes both carriers of
    a board seen at +-45 deg alike): then it may be no other pattern but the same one magnified, and the cause may
    be the water.
    By-hand trial of 7 Dec 2026: a gentle bump wider than a 128^2 field (5 um, sigma 10 mm) magnified the board
    6.5 % and was refused as another pattern with only "record a new reference"."""
    changes = _carrier_changes(expected, measured_freq)
    if any(abs(d) > rotation_tol_deg for _, d in changes):
        return ""
    ratios = [ratio for ratio, _ in changes]  # frequency measured / expected
    change = 1.0 - 0.5 * (ratios[0] + ratios[1])  # above 0: longer periods, the board larger in the frame
    if abs(ratios[0] - ratios[1]) > 0.25 * abs(change):
        return ""
    how = "magnified" if change > 0 else "shrunk"
    return (f". Both periods changed alike, their directions within {rotation_tol_deg:g} deg: the same board {how} "
            f"by {100 * abs(change):.1f} % (alike, or more along one axis), as the lens refocused or the camera "
            "moved along its axis would, or as a water surface curved over the whole view does (a bump or dip wider "
            "than the field acts as a lens, more along the rows than the columns in TIR, which no single frame "
            "tells from a zoom): if the water is what curves, measure a field larger than the feature")


def _tukey(n, taper):
    """Window flat over the middle, cosine-tapered over ``taper / 2`` of each end."""
    x = (np.arange(n) + 0.5) / n
    edge = max(taper / 2.0, 1e-9)
    ramp = np.clip(np.minimum(x, 1.0 - x) / edge, 0.0, 1.0)
    return (0.5 - 0.5 * np.cos(np.pi * ramp)).astype(np.float32)


def _near_carrier_centroids(carriers: Carriers, power, band, fr, fc):
    """``(centroids (2, 2), power)``: the power-weighted mean frequency of the
    band's power within :data:`SMEARED_RADIUS` carrier spacings of each of the
    reference's carriers (NaN where none), and that power in all."""
    rho = SMEARED_RADIUS * carriers.min_spacing
    centroids = np.empty((2, 2))
    near_power = 0.0
    for s, k in enumerate(np.asarray(carriers.freq, dtype=float)):
        # the half-spectrum holds k or -k (f_col >= 0); fold -k onto k
        d_plus = np.hypot(fr - k[0], fc - k[1])
        d_minus = np.hypot(fr + k[0], fc + k[1])
        sign = np.where(d_plus <= d_minus, 1.0, -1.0)
        near = band & (np.minimum(d_plus, d_minus) <= rho)
        w = np.where(near, power, 0.0)
        ws = float(w.sum())
        near_power += ws
        if ws > 0:
            centroids[s] = [float((w * sign * fr).sum()) / ws, float((w * sign * fc).sum()) / ws]
        else:
            centroids[s] = np.nan
    return centroids, near_power


def _check_smeared(carriers: Carriers, frame, no_carrier: NoCarrierError) -> Carriers:
    """The pattern check of a frame without compact carrier peaks.

    A phase-modulated carrier ``A exp(i (k.r + phi))`` keeps its power-weighted
    mean frequency at ``k`` plus the mean phase gradient, however smeared its
    peak; another pattern puts its power elsewhere.  So: the fraction of the
    frame's band power near the reference's carriers and the centroid of that
    power decide; if they refuse the frame, its strongest smoothed peak says
    whether it is another pattern (PatternMismatchError) or none
    (NoCarrierError, re-raised).
    """
    import scipy.ndimage

    img = as_float_image(frame, "frame")
    rows, cols = img.shape
    if float(np.std(img)) == 0.0:
        raise no_carrier
    # flat-topped window: every part of the field weighs the same, so the
    # centroid is the field's mean carrier (a Hann window would weigh a
    # central dimple's compression alone)
    w = _tukey(rows, SMEARED_TAPER)[:, None] * _tukey(cols, SMEARED_TAPER)[None, :]
    spec_c = scipy.fft.rfft2((img - img.mean()) * w, workers=2)
    fr = scipy.fft.fftfreq(rows)[:, None]
    fc = scipy.fft.rfftfreq(cols)[None, :]
    power = (np.abs(spec_c) ** 2).astype(np.float64)
    radius = np.hypot(fr, fc)
    band = (radius >= 4.0 / min(rows, cols)) & (radius <= 1.0 / 2.5)
    total = float(power[band].sum())
    if not total > 0.0:
        raise no_carrier
    centroids, near_power = _near_carrier_centroids(carriers, power, band, fr, fc)
    fraction = near_power / total
    rel, ang = (match_error(carriers, centroids) if np.all(np.isfinite(centroids))
                else (float("inf"), float("inf")))
    if (fraction >= SMEARED_MIN_FRACTION and rel <= SMEARED_PERIOD_TOL
            and ang <= SMEARED_ROTATION_TOL_DEG):
        return Carriers(freq=centroids, shape=(rows, cols), contrast=np.full(2, np.nan),
                        sharpness=np.full(2, np.nan))
    # refused: another pattern, or none?  The smoothed peak standing highest
    # above its ring (geometric mean level, as in find_carriers) decides.
    smooth = scipy.ndimage.gaussian_filter(power, 2.0, mode=("wrap", "nearest"))
    n_rings = max(rows, cols) + 1
    ring = np.minimum((radius * max(rows, cols)).astype(np.int64), n_rings - 1)
    logs = np.log(smooth + 1e-300 + 1e-12 * float(smooth.max()))
    counts = np.bincount(ring[band], minlength=n_rings)
    ring_mean = np.bincount(ring[band], weights=logs[band], minlength=n_rings) / np.maximum(counts, 1)
    score = np.where(band, logs - ring_mean[ring], -np.inf)
    idx = int(np.argmax(score))
    r, c = divmod(idx, score.shape[1])
    contrast = float(np.exp(score[r, c]))
    if contrast < SMEARED_MIN_CONTRAST:
        raise no_carrier
    f = np.array([fr[r, 0], fc[0, c]])
    # the smeared peak's power-weighted centroid: its mean period
    near = band & (np.hypot(fr - f[0], fc - f[1]) <= SMEARED_RADIUS * np.hypot(*f))
    w = np.where(near, power, 0.0)
    f = np.array([float((w * fr).sum()), float((w * fc).sum())]) / float(w.sum())
    period = 1.0 / float(np.hypot(*f))
    angle = math.degrees(math.atan2(f[0], f[1]))
    where = (f"the frame's carriers are {100 * rel:.0f} % off in period and {ang:.0f} deg in direction"
             if np.isfinite(rel) else "no power of the frame lies at the reference's carriers")
    raise PatternMismatchError(
        f"the frame's pattern does not match the reference: measured period about {period:.1f} px "
        f"(the centroid of its strongest, smeared spectral peak, at {angle:.0f} deg), "
        f"expected {carriers.describe()}; only {100 * fraction:.0f} % of the frame's pattern "
        f"power lies near the reference's carriers and {where} (need >= "
        f"{100 * SMEARED_MIN_FRACTION:.0f} % and <= {100 * SMEARED_PERIOD_TOL:.0f} %). Record a "
        "new reference for this pattern, camera position and zoom") from None
