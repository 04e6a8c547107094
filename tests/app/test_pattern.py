"""`tirdeflect pattern`: printed scale of the PDF/SVG/PNG and the suggested period,
checked against the carriers of a ray-traced view of the suggested board."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.batch.pattern import MM_TO_PT, PatternSpec, suggest_period, write_pattern

ROOT = Path(__file__).resolve().parents[2]
PDF_PRECISION_MM = 1e-7  # coordinates are written with 10 significant digits


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def _pdf_numbers(path: Path):
    """MediaBox, stroked line segments and filled rectangles of the PDF's page, in pt,
    read back with pypdf (an independent PDF reader)."""
    pypdf = pytest.importorskip("pypdf")
    from pypdf.generic import ContentStream

    reader = pypdf.PdfReader(str(path))
    assert len(reader.pages) == 1
    page = reader.pages[0]
    box = [float(v) for v in page.mediabox]
    lines, rects, path_ops, text = [], [], [], []
    for operands, op in ContentStream(page.get_contents(), reader).operations:
        values = [float(v) for v in operands] if op in (b"m", b"l", b"re") else operands
        if op in (b"m", b"l"):
            path_ops.append(values)
        elif op == b"S" and len(path_ops) == 2:
            lines.append((*path_ops[0], *path_ops[1]))
            path_ops = []
        elif op == b"re":
            rects.append(tuple(values))
        elif op == b"Tj":
            text.append(str(operands[0]))
    return box, lines, rects, text


@pytest.mark.parametrize("size,period,stretch", [((297.0, 210.0), 2.0, 1.0),
                                                 ((420.0, 297.0), 1.5, 1.0 / math.cos(math.radians(55)))])
def test_pdf_is_at_exact_printed_scale(tmp_path, size, period, stretch):
    out = tmp_path / "board.pdf"
    r = _cli("pattern", "--period-mm", period, "--size-mm", f"{size[0]},{size[1]}",
             "--stretch-y", f"{stretch!r}", "--out", out)
    assert r.returncode == 0, r.stderr
    box, lines, rects, text = _pdf_numbers(out)
    assert any(f"period {period:g} mm" in t for t in text) and "100" in text
    # page size: exactly the requested millimetres (1 mm = 72/25.4 pt)
    assert box[:2] == [0.0, 0.0]
    assert abs(box[2] / MM_TO_PT - size[0]) <= PDF_PRECISION_MM
    assert abs(box[3] / MM_TO_PT - size[1]) <= PDF_PRECISION_MM
    # the ruler: the longest horizontal line, 100 mm, with ticks every millimetre
    horizontal = [(x0, x1) for x0, y0, x1, y1 in lines if y0 == y1]
    x0, x1 = max(horizontal, key=lambda s: abs(s[1] - s[0]))
    assert abs((x1 - x0) / MM_TO_PT - 100.0) <= 2 * PDF_PRECISION_MM
    ticks = sorted(a for a, y0, b, y1 in lines if a == b)
    assert len(ticks) == 101
    assert np.max(np.abs(np.diff(ticks) / MM_TO_PT - 1.0)) <= 2 * PDF_PRECISION_MM
    # the cells: period/2 wide, period*stretch/2 high (interior cells; edge cells are clipped)
    widths = np.array([w for _, _, w, _ in rects]) / MM_TO_PT
    heights = np.array([h for _, _, _, h in rects]) / MM_TO_PT
    assert np.median(widths) == pytest.approx(period / 2, abs=PDF_PRECISION_MM)
    assert np.median(heights) == pytest.approx(period * stretch / 2, abs=PDF_PRECISION_MM)
    assert widths.max() <= period / 2 + PDF_PRECISION_MM


def test_svg_in_millimetres(tmp_path):
    out = tmp_path / "board.svg"
    write_pattern(PatternSpec(2.0, 297.0, 210.0), out)
    text = out.read_text()
    assert 'width="297mm" height="210mm" viewBox="0 0 297 210"' in text
    widths = [float(w) for w in re.findall(r'<rect x="[\d.e-]+" y="[\d.e-]+" width="([\d.e-]+)"', text)]
    assert np.median(widths) == 1.0


def test_png_period_in_pixels_at_the_chosen_dpi(tmp_path):
    from PIL import Image

    out = tmp_path / "board.png"
    dpi, period = 300.0, 2.0
    write_pattern(PatternSpec(period, 150.0, 60.0, margin_mm=25.0), out, dpi=dpi)
    im = Image.open(out)
    assert im.info["dpi"] == pytest.approx((dpi, dpi), abs=0.01)
    assert im.size == (round(150 / 25.4 * dpi), round(60 / 25.4 * dpi))
    # edges along a row through the middle of the first cell row: 50 % crossings,
    # sub-pixel by the exact area coverage of each pixel
    row = np.asarray(im, dtype=float)[int(0.5 * period / 2 / 25.4 * dpi)] / 255.0
    k = np.nonzero(np.diff(np.sign(row - 0.5)))[0]
    edges = k + (0.5 - row[k]) / (row[k + 1] - row[k]) + 0.5
    spacing = np.diff(edges)
    assert np.mean(spacing) == pytest.approx(period / 2 / 25.4 * dpi, abs=0.01)


def test_page_too_small_for_the_ruler_is_a_one_line_error(tmp_path):
    r = _cli("pattern", "--period-mm", "2", "--size-mm", "80,80", "--out", tmp_path / "b.pdf")
    assert r.returncode == 2 and "ruler" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "b.pdf").exists()


def test_suggested_period_puts_the_carriers_where_stated():
    """Ray-trace the flat surface over the suggested board (telecentric camera, theta 55 deg)
    and find its carriers: their periods along columns and rows are what --suggest says."""
    from processing import Geometry, forward
    from processing.carriers import find_carriers

    theta, pixel_mm = 55.0, 0.08
    s = suggest_period(theta, 300.0, pixel_mm, (1024, 1024))
    px_x, px_y = s.period_px_square
    assert 10 <= px_y <= px_x <= 20
    assert math.sqrt(px_x * px_y) == pytest.approx(14.0, rel=0.05 / s.period_mm)  # 0.05 mm rounding
    assert s.period_px_stretched[0] == s.period_px_stretched[1]
    geometry = Geometry.from_dict({"setup": "tir", "theta_deg": theta, "depth_mm": 300.0,
                                   "pixel_mm": pixel_mm, "rows_toward_camera": False})
    image, _ = forward.render(forward.FlatSurface(), geometry, (256, 256),
                              forward.Checkerboard(period_mm=s.period_mm, edge_softness_mm=pixel_mm))
    carriers = find_carriers(image)
    f_row, f_col = np.abs(np.asarray(carriers.freq)).max(axis=0)
    assert 1 / f_col == pytest.approx(px_x, rel=0.01)
    assert 1 / f_row == pytest.approx(px_y, rel=0.01)
    assert carriers.theta_deg == pytest.approx(theta, abs=0.5)


def test_suggest_prints_the_rule():
    r = _cli("pattern", "--suggest", "--theta-deg", "55", "--depth-mm", "300", "--pixel-mm", "0.08",
             "--camera", "1024x1024")
    assert r.returncode == 0, r.stderr
    assert "rule: image periods between 10 and 20 px" in r.stdout
    assert "suggested period: 1.5 mm" in r.stdout and "1/cos(theta) = 1.7434" in r.stdout
    r = _cli("pattern", "--suggest", "--theta-deg", "40", "--depth-mm", "300", "--pixel-mm", "0.08",
             "--camera", "1024x1024")
    assert r.returncode == 2 and "critical angle" in r.stderr


def test_stretched_board_looks_square_and_theta_accounts_for_it():
    """The board stretched by 1/cos(theta) along y, ray traced: equal image periods along
    both axes (the suggestion), and theta estimated from the carriers is right only once
    the geometry's pattern_stretch_y divides the stretch out."""
    from processing import Geometry, Reconstructor, forward
    from processing.carriers import find_carriers, theta_from_carriers

    theta, pixel_mm = 55.0, 0.08
    s = suggest_period(theta, 300.0, pixel_mm, (1024, 1024))
    board = forward.Checkerboard(period_mm=s.period_stretched_mm, edge_softness_mm=pixel_mm)

    def stretched(x_mm, y_mm):
        return board(x_mm, np.asarray(y_mm) / s.stretch_y)

    geometry = Geometry.from_dict({"setup": "tir", "theta_deg": theta, "depth_mm": 300.0,
                                   "pixel_mm": pixel_mm, "rows_toward_camera": False,
                                   "pattern_stretch_y": s.stretch_y})
    assert Geometry.from_toml_text(geometry.to_toml_text()) == geometry
    image, _ = forward.render(forward.FlatSurface(), geometry, (256, 256), stretched)
    carriers = find_carriers(image)
    f_row, f_col = np.abs(np.asarray(carriers.freq)).max(axis=0)
    assert 1 / f_col == pytest.approx(s.period_px_stretched[0], rel=0.01)
    assert 1 / f_row == pytest.approx(s.period_px_stretched[1], rel=0.01)
    # a square-board reading says the camera looks straight on; the stretch fixes it
    assert not abs(theta_from_carriers(carriers.freq) - theta) < 5
    assert theta_from_carriers(carriers.freq, s.stretch_y) == pytest.approx(theta, abs=0.5)
    alignment = Reconstructor(image, geometry).alignment(image)
    assert alignment["theta_estimate_deg"] == pytest.approx(theta, abs=0.5)
