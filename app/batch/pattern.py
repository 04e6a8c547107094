"""The printed checkerboard (``tirdeflect pattern``): a period suited to the camera
and theta, and the board itself at exact printed scale.

Scale
-----
The PDF page is exactly ``--size-mm W,H`` (1 mm = 72/25.4 pt, every
coordinate written with 10 significant digits: a few nanometres on A0; the
PDF is written directly because reportlab rounds to 6 digits, 0.06 um off on
A3). The checkerboard fills the page above a margin
strip (``margin_mm``, bottom) that holds a 100 mm ruler with millimetre ticks
and the board's parameters, so a print can be checked with a ruler: print at
100 % ("actual size"), never "fit to page". SVG is written in mm units (exact
at any resolution); PNG at ``dpi`` pixels per inch, anti-aliased by exact
area coverage of each pixel, with the DPI stored in the file.

Size
----
The vector files describe the board, they do not draw each square: a
checkerboard is the exclusive-or of its dark columns and its light rows, so
one path of ``n_columns/2 + n_rows/2`` full-length stripes filled with the
even-odd rule (PDF ``f*``, SVG ``fill-rule="evenodd"``) is the whole board:
a 200 x 200 mm board at a 2 mm period is 200 rectangles, not 10000. The board
is still bounded by what can be printed and used: squares no smaller than
:data:`MIN_SQUARE_MM` (about one dot of a 1200 dpi printer), at most
:data:`MAX_SQUARES` of them (a 25 Mpx camera resolving 10 px per period sees
about half a million squares: more is a typo of the period or of the size),
PDF pages no larger than :data:`PDF_MAX_PAGE_MM` (200 in, the 14400 pt
implementation limit of the PDF reference that Acrobat and print drivers
enforce). A PNG is a raster held in memory: it is refused, with the memory it
would need, when that exceeds :data:`PNG_MAX_BYTES`, before anything is
allocated.

The period
----------
``period_mm`` is the full period (one dark plus one bright square), as in
:class:`processing.forward.Checkerboard`. A telecentric camera looking at the
surface under incidence theta sees a square board with an x-period
``P / s`` and a y-period ``P cos(theta) / s`` pixels (``s`` = ``pixel_mm``,
notes.md). A board stretched by ``1/cos(theta)`` along y (cells
``P/2`` by ``P/(2 cos theta)``) shows square cells, ``P / s`` pixels along
both axes; the theta estimate from the carriers must then be told the stretch
(geometry key ``pattern_stretch_y``).

Rule of :func:`suggest_period`: the two image periods should lie between
:data:`MIN_PERIOD_PX` and :data:`MAX_PERIOD_PX` pixels. Below ~10 px the
checkerboard's third harmonics fold back next to the carriers and the pass
band (radius about half the carrier spacing) gets too narrow for the pixel
blur of the edges; above ~20 px the demodulated displacement is smoothed over
more surface (features of 25-45 px lose ~4 % of their amplitude at 11-20 px
periods, notes.md) and fewer periods fit the field. The period chosen puts
the geometric mean of the two image periods at :data:`TARGET_PERIOD_PX`
(14 px), rounded to 0.05 mm; for the stretched board (equal periods) both
at 14 px. A camera at a finite distance ``D`` (``--camera-distance-mm``) sees
the board, ``H / cos(theta)`` beyond the surface, smaller by ``m = D / (D +
H / cos(theta))`` at the image centre (the geometry's two magnifications,
notes.md): the periods above are divided by ``m``'s effect, ``s / m`` in place
of ``s`` (by-hand trial of 7 Dec 2026: a suggestion of 18.8 / 10.8 px, made for
a telecentric lens, showed 13.9 / 8.0 px to a camera 1500 mm away). Without it
the suggestion says that it assumes a telecentric lens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from processing.errors import TirdeflectError

__all__ = ["PatternSpec", "Suggestion", "suggest_period", "board_shrink", "write_pattern", "MM_TO_PT",
           "RULER_MM", "TARGET_PERIOD_PX", "MIN_PERIOD_PX", "MAX_PERIOD_PX", "MIN_SQUARE_MM",
           "MAX_SQUARES", "PDF_MAX_PAGE_MM", "PNG_MAX_BYTES", "png_bytes_needed"]

#: PDF points per millimetre (1 pt = 1/72 inch, 1 inch = 25.4 mm).
MM_TO_PT = 72.0 / 25.4
RULER_MM = 100.0
TARGET_PERIOD_PX = 14.0
MIN_PERIOD_PX = 10.0
MAX_PERIOD_PX = 20.0
N_CRITICAL_DEG = math.degrees(math.asin(1 / 1.333))
#: Smallest square side that a printer can render, mm (one dot at 1200 dpi is 0.021 mm).
MIN_SQUARE_MM = 0.02
#: Most squares on one board (see the module docstring).
MAX_SQUARES = 10_000_000
#: Largest PDF page side, mm: 14400 pt = 200 in (PDF reference, implementation limits).
PDF_MAX_PAGE_MM = 14400 / (72.0 / 25.4)
#: Largest memory a PNG board may take while it is drawn, bytes.
PNG_MAX_BYTES = 1_500_000_000
#: Rows of the PNG computed at a time (float64 temporaries of this many pixels).
_PNG_BLOCK_PIXELS = 1 << 22


@dataclass(frozen=True)
class PatternSpec:
    """A printable checkerboard.

    Attributes
    ----------
    period_mm : float
        Full period along x (two squares), mm.
    width_mm, height_mm : float
        Page size, mm.
    stretch_y : float
        Cell height / cell width (1: square cells; ``1/cos(theta)``: seen square).
    margin_mm : float
        Bottom strip for the ruler and the parameters, mm.
    """

    period_mm: float
    width_mm: float
    height_mm: float
    stretch_y: float = 1.0
    margin_mm: float = 25.0
    note: str = ""

    def check(self) -> None:
        for name in ("period_mm", "width_mm", "height_mm", "stretch_y"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise TirdeflectError(f"{name.replace('_mm', '')} must be a positive number; got {value}")
        if self.width_mm < RULER_MM + 10:
            raise TirdeflectError(
                f"the page is {self.width_mm:g} mm wide: the {RULER_MM:g} mm check ruler needs at least "
                f"{RULER_MM + 10:g} mm; print on a wider sheet (and cut the board out)")
        if not 15 <= self.margin_mm < self.height_mm:
            raise TirdeflectError(f"--margin-mm must be >= 15 (ruler and text) and less than the page height; "
                                  f"got {self.margin_mm:g}")
        board_h = self.height_mm - self.margin_mm
        if min(self.width_mm / self.period_mm, board_h / (self.period_mm * self.stretch_y)) < 4:
            raise TirdeflectError(
                f"a {self.period_mm:g} mm period gives fewer than 4 periods on a {self.width_mm:g} x "
                f"{board_h:g} mm board; carriers need many periods: use a smaller period or a larger page")
        side = min(self.cell_w_mm, self.cell_h_mm)
        if side < MIN_SQUARE_MM:
            raise TirdeflectError(
                f"--period-mm {self.period_mm:g} gives squares of {side:.3g} mm, smaller than a printer can "
                f"draw (about {MIN_SQUARE_MM:g} mm, one dot at 1200 dpi); use a period of at least "
                f"{2 * MIN_SQUARE_MM / min(1.0, self.stretch_y):g} mm (tirdeflect pattern --suggest "
                f"proposes one for the camera)")
        n_cols, n_rows = self.grid
        if n_cols * n_rows > MAX_SQUARES:
            raise TirdeflectError(
                f"a {self.width_mm:g} x {board_h:g} mm board at a {self.period_mm:g} mm period holds "
                f"{n_cols} x {n_rows} = {n_cols * n_rows:.3g} squares, more than the {MAX_SQUARES:.0e} a "
                f"print needs (a 25 Mpx camera resolving 10 px per period sees about 5e5 squares); use a "
                f"larger --period-mm (at least {self.period_mm * math.sqrt(n_cols * n_rows / MAX_SQUARES):.3g}"
                f" mm for this page) or a smaller --size-mm")

    @property
    def grid(self) -> tuple:
        """(columns, rows) of squares on the board, the last ones possibly clipped."""
        board_h = self.height_mm - self.margin_mm
        return (int(math.ceil(self.width_mm / self.cell_w_mm - 1e-9)),
                int(math.ceil(board_h / self.cell_h_mm - 1e-9)))

    @property
    def cell_w_mm(self) -> float:
        return self.period_mm / 2.0

    @property
    def cell_h_mm(self) -> float:
        return self.period_mm * self.stretch_y / 2.0

    def describe(self) -> str:
        text = (f"tirdeflect checkerboard: period {self.period_mm:g} mm along x (squares "
                f"{self.cell_w_mm:g} mm)")
        if abs(self.stretch_y - 1) > 1e-12:
            text += f", cells stretched {self.stretch_y:.4f}x along y ({self.cell_h_mm:.4f} mm)"
        return text + f"; page {self.width_mm:g} x {self.height_mm:g} mm"


def stripes(spec: PatternSpec):
    """The board as (x_mm, y_mm, w_mm, h_mm) rectangles whose even-odd fill is the checkerboard.

    Cell ``(i, j)`` (column, row) is dark where ``i + j`` is even, i.e. where
    "column i is even" and "row j is odd" are not both true nor both false:
    the even columns (full board height) and the odd rows (full page width),
    filled with the even-odd rule, cover exactly the dark cells (a light
    cell is covered by both or by neither). ``y`` runs down from the top of
    the page; the last column and row are clipped to the board (the page
    above the margin).
    """
    board_h = spec.height_mm - spec.margin_mm
    cw, ch = spec.cell_w_mm, spec.cell_h_mm
    n_cols, n_rows = spec.grid
    out = []
    for i in range(0, n_cols, 2):
        x0, x1 = i * cw, min((i + 1) * cw, spec.width_mm)
        out.append((x0, 0.0, x1 - x0, board_h))
    for j in range(1, n_rows, 2):
        y0, y1 = j * ch, min((j + 1) * ch, board_h)
        out.append((0.0, y0, spec.width_mm, y1 - y0))
    return out


def ruler_ticks():
    """(position_mm, length_mm, label) of the ruler's ticks, 0..100 mm."""
    ticks = []
    for k in range(int(RULER_MM) + 1):
        if k % 10 == 0:
            ticks.append((float(k), 4.0, str(k)))
        elif k % 5 == 0:
            ticks.append((float(k), 2.8, ""))
        else:
            ticks.append((float(k), 1.8, ""))
    return ticks


def _margin_lines(spec: PatternSpec) -> list:
    lines = [spec.describe()]
    if spec.note:
        lines.append(spec.note)
    lines.append(f"Print at 100 % (actual size, not 'fit to page'): the ruler must measure "
                 f"{RULER_MM:g} mm.")
    return lines


# =========================================================================== writers


def write_pattern(spec: PatternSpec, path, *, dpi: float = 600.0, overwrite: bool = False) -> Path:
    """Write the board as .pdf (vector), .svg (vector, mm units) or .png (``dpi``)."""
    spec.check()
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".pdf", ".svg", ".png"):
        raise TirdeflectError(f"--out {str(p)!r}: give a .pdf, .svg or .png file name")
    if p.exists() and not overwrite:
        raise TirdeflectError(f"{str(p)!r} already exists; choose another --out or add --overwrite")
    if not (p.parent if str(p.parent) else Path(".")).is_dir():
        raise TirdeflectError(f"the folder of --out {str(p)!r} does not exist; create it first")
    if suffix == ".pdf" and max(spec.width_mm, spec.height_mm) > PDF_MAX_PAGE_MM:
        raise TirdeflectError(
            f"a {spec.width_mm:g} x {spec.height_mm:g} mm page is larger than a PDF page can be "
            f"({PDF_MAX_PAGE_MM:.0f} mm = 200 in per side, the limit viewers and print drivers enforce); "
            f"write an .svg (mm units, no page limit) or print the board in tiles of at most "
            f"{PDF_MAX_PAGE_MM:.0f} mm")
    if suffix == ".png":
        if not (50 <= dpi <= 4800):
            raise TirdeflectError(f"--dpi must be between 50 and 4800; got {dpi:g}")
        need = png_bytes_needed(spec, dpi)
        if need > PNG_MAX_BYTES:
            scale = math.sqrt(need / PNG_MAX_BYTES)
            raise TirdeflectError(
                f"a {spec.width_mm:g} x {spec.height_mm:g} mm PNG at {dpi:g} dpi needs about "
                f"{need / 1e9:.3g} GB of memory, more than the {PNG_MAX_BYTES / 1e9:g} GB allowed; write "
                f"a .pdf or .svg (vector, any resolution, a few kB), lower --dpi (at most "
                f"{dpi / scale:.0f} for this page) or use a smaller --size-mm")
    if suffix == ".pdf":
        _write_pdf(spec, p)
    elif suffix == ".svg":
        _write_svg(spec, p)
    else:
        _write_png(spec, p, dpi)
    return p


def _png_shape(spec: PatternSpec, dpi: float) -> tuple:
    px_per_mm = dpi / 25.4
    return int(round(spec.height_mm * px_per_mm)), int(round(spec.width_mm * px_per_mm))


def png_bytes_needed(spec: PatternSpec, dpi: float) -> int:
    """Peak memory of :func:`_write_png`, bytes: the 8-bit image, Pillow's copy of it
    for the ruler and text, and the float64 temporaries of one block of rows."""
    rows, cols = _png_shape(spec, dpi)
    block = max(1, min(rows, _PNG_BLOCK_PIXELS // max(cols, 1))) * cols
    return 2 * rows * cols + 4 * 8 * block


def _num(value: float) -> str:
    """A PDF number with 10 significant digits (reportlab keeps 6: 1190.551 pt for 420 mm)."""
    text = f"{value:.10g}"
    return "0" if text in ("-0", "0") else text


def _pdf_text(text: str) -> str:
    data = text.encode("cp1252", errors="replace").decode("latin-1")
    return data.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")


def _write_pdf(spec: PatternSpec, p: Path) -> None:
    """One-page vector PDF written directly: filled rectangles, stroked lines and
    Helvetica text (a standard font, nothing embedded); every coordinate in pt with
    10 significant digits, so the printed scale is exact to far below a micrometre."""
    W, H = spec.width_mm, spec.height_mm
    pt = MM_TO_PT
    ops = ["0 g 0 G"]
    for x, y, w, h in stripes(spec):  # PDF y runs up from the bottom of the page
        ops.append(f"{_num(x * pt)} {_num((H - y - h) * pt)} {_num(w * pt)} {_num(h * pt)} re")
    ops.append("f*")  # even-odd: the stripes' exclusive-or is the checkerboard
    x0, y0 = 5.0, 8.0  # ruler baseline: 100 mm long, 8 mm above the bottom edge
    ops.append(f"{_num(0.15 * pt)} w 0 J")
    ops.append(f"{_num(x0 * pt)} {_num(y0 * pt)} m {_num((x0 + RULER_MM) * pt)} {_num(y0 * pt)} l S")
    size_small, size_text = 6.0, 7.0
    labels = []
    for pos, length, label in ruler_ticks():
        x = (x0 + pos) * pt
        ops.append(f"{_num(x)} {_num(y0 * pt)} m {_num(x)} {_num((y0 + length) * pt)} l S")
        if label:  # Helvetica digits are 0.556 em wide: centre the label under its tick
            labels.append((x - 0.556 * size_small * len(label) / 2, (y0 - 3.0) * pt, size_small, label))
    labels.append(((x0 + RULER_MM + 2) * pt, y0 * pt, size_small, "mm"))
    for k, text in enumerate(_margin_lines(spec)):
        labels.append((x0 * pt, (spec.margin_mm - 5.0 - 3.2 * k) * pt, size_text, text))
    for x, y, size, text in labels:
        ops.append(f"BT /F1 {_num(size)} Tf {_num(x)} {_num(y)} Td ({_pdf_text(text)}) Tj ET")
    import zlib

    content = zlib.compress("\n".join(ops).encode("latin-1"), 9)
    info = (f"<< /Title (tirdeflect checkerboard) /Subject ({_pdf_text(spec.describe())}) "
            f"/Creator (tirdeflect pattern) >>")
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(W * pt)} {_num(H * pt)}] "
         f"/Resources << /Font << /F1 4 0 R >> >> /Contents 5 0 R >>").encode("latin-1"),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        b"<< /Length " + str(len(content)).encode() + b" /Filter /FlateDecode >>\nstream\n"
        + content + b"\nendstream",
        info.encode("latin-1"),
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for k, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{k} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode()
    for offset in offsets:
        out += f"{offset:010d} 00000 n \n".encode()
    out += (f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R /Info 6 0 R >>\n"
            f"startxref\n{xref}\n%%EOF\n").encode()
    p.write_bytes(bytes(out))


def _write_svg(spec: PatternSpec, p: Path) -> None:
    from xml.sax.saxutils import escape

    W, H = spec.width_mm, spec.height_mm
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W:.10g}mm" height="{H:.10g}mm" '
        f'viewBox="0 0 {W:.10g} {H:.10g}">',
        f"<title>{escape(spec.describe())}</title>",
        f'<rect x="0" y="0" width="{W:.10g}" height="{H:.10g}" fill="white"/>',
    ]
    # one even-odd path of stripes: their exclusive-or is the checkerboard (see stripes())
    path = " ".join(f"M{x:.10g} {y:.10g}h{w:.10g}v{h:.10g}h{-w:.10g}z" for x, y, w, h in stripes(spec))
    parts.append(f'<path fill="black" fill-rule="evenodd" shape-rendering="crispEdges" d="{path}"/>')
    x0, y0 = 5.0, H - 8.0
    parts.append('<g stroke="black" stroke-width="0.15" fill="none">')
    parts.append(f'<line x1="{x0}" y1="{y0:.10g}" x2="{x0 + RULER_MM}" y2="{y0:.10g}"/>')
    for pos, length, _ in ruler_ticks():
        parts.append(f'<line x1="{x0 + pos:.10g}" y1="{y0:.10g}" x2="{x0 + pos:.10g}" '
                     f'y2="{y0 - length:.10g}"/>')
    parts.append("</g>")
    parts.append('<g font-family="Helvetica, Arial, sans-serif" font-size="2.1" fill="black">')
    for pos, _, label in ruler_ticks():
        if label:
            parts.append(f'<text x="{x0 + pos:.10g}" y="{y0 + 3:.10g}" text-anchor="middle">{label}</text>')
    parts.append(f'<text x="{x0 + RULER_MM + 2:.10g}" y="{y0:.10g}">mm</text>')
    for k, text in enumerate(_margin_lines(spec)):
        parts.append(f'<text x="{x0}" y="{H - spec.margin_mm + 5.0 + 3.2 * k + 2:.10g}" '
                     f'font-size="2.5">{escape(text)}</text>')
    parts += ["</g>", "</svg>", ""]
    p.write_text("\n".join(parts), encoding="utf-8")


def _square_wave_coverage(n_px: int, half_period_px: float, limit_px: float) -> np.ndarray:
    """Fraction of pixel k (covering [k, k+1)) that lies in 'even' intervals
    [2m h, (2m+1) h) of a square wave of half-period h, cut at ``limit_px``."""
    def dark(x):
        x = np.minimum(x, limit_px)
        period = 2 * half_period_px
        m = np.floor(x / period)
        return m * half_period_px + np.minimum(x - m * period, half_period_px)
    k = np.arange(n_px + 1, dtype=np.float64)
    return np.diff(dark(k))


def _write_png(spec: PatternSpec, p: Path, dpi: float) -> None:
    from PIL import Image

    px_per_mm = dpi / 25.4
    rows, cols = _png_shape(spec, dpi)
    board_rows = (spec.height_mm - spec.margin_mm) * px_per_mm
    # exact area coverage: a cell is dark where (i + j) is even, i.e. where the
    # x and y square waves agree: cov = cx*cy + (1-cx)*(1-cy) inside the board
    cx = _square_wave_coverage(cols, spec.cell_w_mm * px_per_mm, cols)
    inside_y = np.clip(board_rows - np.arange(rows), 0.0, 1.0)
    cy = _square_wave_coverage(rows, spec.cell_h_mm * px_per_mm, board_rows)
    image = np.empty((rows, cols), dtype=np.uint8)
    step = max(1, _PNG_BLOCK_PIXELS // max(cols, 1))  # bounded temporaries (png_bytes_needed)
    for r0 in range(0, rows, step):
        r1 = min(rows, r0 + step)
        dark = np.outer(cy[r0:r1], cx) + np.outer(inside_y[r0:r1] - cy[r0:r1], 1.0 - cx)
        image[r0:r1] = np.round(255.0 * (1.0 - dark))
    # ruler and text in the margin, drawn with Pillow at the same scale
    from PIL import ImageDraw, ImageFont

    im = Image.fromarray(image)
    draw = ImageDraw.Draw(im)
    try:  # Pillow >= 10.1: a scalable default font, sized in mm like the PDF's
        small = ImageFont.load_default(size=max(8, int(round(2.1 * px_per_mm))))
        text_font = ImageFont.load_default(size=max(8, int(round(2.5 * px_per_mm))))
    except TypeError:
        small = text_font = ImageFont.load_default()
    x0, y0 = 5.0, spec.height_mm - 8.0
    line_w = max(1, int(round(0.15 * px_per_mm)))
    def xy(x_mm, y_mm):
        return (x_mm * px_per_mm, y_mm * px_per_mm)
    draw.line([xy(x0, y0), xy(x0 + RULER_MM, y0)], fill=0, width=line_w)
    for pos, length, label in ruler_ticks():
        draw.line([xy(x0 + pos, y0), xy(x0 + pos, y0 - length)], fill=0, width=line_w)
        if label:
            draw.text(xy(x0 + pos, y0 + 1), label, fill=0, font=small, anchor="mt")
    for k, text in enumerate(_margin_lines(spec)):
        draw.text(xy(x0, spec.height_mm - spec.margin_mm + 3 + 3.2 * k), text, fill=0, font=text_font)
    im.save(p, dpi=(dpi, dpi))


# =========================================================================== the period


@dataclass
class Suggestion:
    """A period for the camera and geometry, and what it gives (see the module docstring)."""

    period_mm: float
    theta_deg: float
    pixel_mm: float
    depth_mm: float
    camera: tuple
    period_px_square: tuple  # (x/cols, y/rows) image periods of a square board, px
    period_stretched_mm: float  # period for the board stretched by 1/cos(theta)
    period_px_stretched: tuple  # its image periods, px
    stretch_y: float
    field_mm: tuple  # surface field of view (x, y), mm
    board_mm: tuple  # suggested board size (x, y), mm
    wrap_slope_x: float  # largest |dh/dx| before the x-carrier phase wraps (no unwrapping)
    warnings: list = field(default_factory=list)
    camera_distance_mm: float | None = None  # None: a telecentric lens

    @property
    def board_shrink(self) -> float:
        """How much smaller the camera sees the board than the surface at the image centre: ``D / (D +
        H / cos(theta))``, 1 for a telecentric lens."""
        return board_shrink(self.theta_deg, self.depth_mm, self.camera_distance_mm)

    def _camera_line(self) -> str:
        beyond = self.depth_mm / math.cos(math.radians(self.theta_deg))
        if self.camera_distance_mm is None:
            example = board_shrink(self.theta_deg, self.depth_mm, 1500.0)
            return (f"camera: this suggestion assumes a telecentric lens (no --camera-distance-mm); a camera at a "
                    f"finite distance D sees the board, H / cos(theta) = {beyond:.4g} mm beyond the surface, "
                    f"smaller by D / (D + {beyond:.4g} mm) ({example:.3f} at 1500 mm): give --camera-distance-mm D "
                    f"(camera_distance_mm in the geometry) for its periods")
        return (f"camera {self.camera_distance_mm:g} mm away: it sees the board, H / cos(theta) = {beyond:.4g} mm "
                f"beyond the surface, smaller by {self.board_shrink:.4f} at the image centre, so the periods "
                f"are for {self.pixel_mm / self.board_shrink:.4g} mm of board per column (pixel_mm / "
                f"{self.board_shrink:.4f}); they change across the image (keystone)")

    def lines(self) -> list:
        sx, sy = self.period_px_square
        tx, ty = self.period_px_stretched
        out = [
            f"rule: image periods between {MIN_PERIOD_PX:g} and {MAX_PERIOD_PX:g} px along both image "
            f"axes, geometric mean {TARGET_PERIOD_PX:g} px (square board: x-period P/s, y-period "
            f"P cos(theta)/s; s = {self.pixel_mm / self.board_shrink:.4g} mm "
            f"{'per column' if self.camera_distance_mm is None else 'of board per column at the image centre'})",
            f"suggested period: {self.period_mm:g} mm (squares {self.period_mm / 2:g} mm); set "
            f"pattern_period_mm = {self.period_mm:g} in the geometry, and the reference is checked against pixel_mm",
            f"  square board:    {sx:.1f} px per period along x (columns), {sy:.1f} px along y (rows)",
            f"or a board stretched by 1/cos(theta) = {self.stretch_y:.4f} along y (--stretch-y "
            f"{self.stretch_y:.4f}), seen with square cells: period {self.period_stretched_mm:g} mm, cells "
            f"{self.period_stretched_mm / 2:g} x {self.period_stretched_mm * self.stretch_y / 2:.4g} mm: "
            f"{tx:.1f} px along x, {ty:.1f} px along y; then set pattern_stretch_y = {self.stretch_y:.4f} "
            f"(theta estimated from the carriers accounts for the stretch) and pattern_period_mm = "
            f"{self.period_stretched_mm:g} in the geometry",
            f"field of view on the surface: {self.field_mm[0]:.1f} x {self.field_mm[1]:.1f} mm "
            f"({self.camera[0]} x {self.camera[1]} px); board at least {self.board_mm[0]:g} x "
            f"{self.board_mm[1]:g} mm (field + 20 %)",
            f"phase of the x-carrier wraps at |dh/dx| = {self.wrap_slope_x:.2e} (P / 4H at H = "
            f"{self.depth_mm:g} mm); steeper waves need unwrapping (on by default)",
            self._camera_line(),
        ]
        return out + [f"warning: {w}" for w in self.warnings]


def board_shrink(theta_deg: float, depth_mm: float, camera_distance_mm: float | None) -> float:
    """``D / (D + H / cos(theta))``: how much smaller a camera ``D`` mm away sees the board than the surface at
    the image centre (1: a telecentric lens, ``D`` None)."""
    if camera_distance_mm is None:
        return 1.0
    return camera_distance_mm / (camera_distance_mm + depth_mm / math.cos(math.radians(theta_deg)))


def suggest_period(theta_deg: float, depth_mm: float, pixel_mm: float, camera: tuple,
                   camera_distance_mm: float | None = None) -> Suggestion:
    """Period (mm) putting the geometric mean of the two image periods at
    :data:`TARGET_PERIOD_PX`, rounded to 0.05 mm (rule in the module docstring), for a telecentric lens
    (``camera_distance_mm`` None) or a camera that far from the surface centre."""
    if not (N_CRITICAL_DEG < theta_deg < 90):
        raise TirdeflectError(f"--theta-deg must be above the critical angle {N_CRITICAL_DEG:.1f} deg "
                              f"(total internal reflection) and below 90; got {theta_deg:g}")
    for name, value in (("--depth-mm", depth_mm), ("--pixel-mm", pixel_mm)) + (
            (("--camera-distance-mm", camera_distance_mm),) if camera_distance_mm is not None else ()):
        if not (math.isfinite(value) and value > 0):
            raise TirdeflectError(f"{name} must be a positive number of mm; got {value:g}")
    cols, rows = camera
    c = math.cos(math.radians(theta_deg))
    board_px_mm = pixel_mm / board_shrink(theta_deg, depth_mm, camera_distance_mm)  # board mm per column
    # square board: x = P/s, y = P c/s; geometric mean P sqrt(c)/s = target
    period = TARGET_PERIOD_PX * board_px_mm / math.sqrt(c)
    period = max(0.05, round(period / 0.05) * 0.05)
    square = (period / board_px_mm, period * c / board_px_mm)
    period_st = max(0.05, round(TARGET_PERIOD_PX * board_px_mm / 0.05) * 0.05)
    stretched = (period_st / board_px_mm, period_st / board_px_mm)
    field_mm = (cols * pixel_mm, rows * pixel_mm / c)
    board = tuple(float(math.ceil(1.2 * v / 10.0) * 10) for v in field_mm)
    warnings = []
    if not (MIN_PERIOD_PX <= square[1] and square[0] <= MAX_PERIOD_PX):
        warnings.append(f"at theta {theta_deg:g} deg a square board cannot keep both image periods within "
                        f"{MIN_PERIOD_PX:g}-{MAX_PERIOD_PX:g} px ({square[0]:.1f} and {square[1]:.1f}): "
                        f"print the stretched board (--stretch-y {1 / c:.4f})")
    if min(cols / square[0], rows / square[1]) < 10:
        warnings.append("fewer than 10 periods fit across the image: the carrier search needs about ten; "
                        "use more pixels or a smaller pixel_mm")
    return Suggestion(period, theta_deg, pixel_mm, depth_mm, (cols, rows), square, period_st, stretched, 1 / c,
                      field_mm, board, period / (4 * depth_mm), warnings, camera_distance_mm)
