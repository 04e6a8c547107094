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
    """MediaBox, stroked line segments, rectangles and fill operators of the PDF's page, in pt,
    read back with pypdf (an independent PDF reader)."""
    pypdf = pytest.importorskip("pypdf")
    from pypdf.generic import ContentStream

    reader = pypdf.PdfReader(str(path))
    assert len(reader.pages) == 1
    page = reader.pages[0]
    box = [float(v) for v in page.mediabox]
    lines, rects, path_ops, text, fill_ops = [], [], [], [], []
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
        elif op in (b"f", b"F", b"f*", b"B", b"B*", b"b", b"b*"):
            fill_ops.append(op)
    return box, lines, rects, text, fill_ops


@pytest.mark.parametrize("size,period,stretch", [((297.0, 210.0), 2.0, 1.0),
                                                 ((420.0, 297.0), 1.5, 1.0 / math.cos(math.radians(55)))])
def test_pdf_is_at_exact_printed_scale(tmp_path, size, period, stretch):
    out = tmp_path / "board.pdf"
    r = _cli("pattern", "--period-mm", period, "--size-mm", f"{size[0]},{size[1]}",
             "--stretch-y", f"{stretch!r}", "--out", out)
    assert r.returncode == 0, r.stderr
    box, lines, rects, text, fill_ops = _pdf_numbers(out)
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
    # the board is one even-odd path of stripes (f*), a few hundred rectangles, not one per square
    assert fill_ops == [b"f*"] and len(rects) < 400
    # what it fills, by the even-odd rule at each cell's centre: dark where column + row is even,
    # cells period/2 wide and period*stretch/2 high, from the top-left corner of the page
    cw, ch = period / 2, period * stretch / 2
    board_h = size[1] - 25.0
    xc = (np.arange(int(size[0] / cw)) + 0.5) * cw
    yc = (np.arange(int(board_h / ch)) + 0.5) * ch
    X, Y = np.meshgrid(xc * MM_TO_PT, (size[1] - yc) * MM_TO_PT)  # PDF y runs up
    covered = sum(((X > x) & (X < x + w) & (Y > y) & (Y < y + h)).astype(int) for x, y, w, h in rects)
    i, j = np.meshgrid(np.arange(xc.size), np.arange(yc.size))
    np.testing.assert_array_equal(covered % 2 == 1, (i + j) % 2 == 0)
    # every edge at its exact printed place: the stripes' sides are multiples of the cell size
    # (to the 10th digit of a coordinate up to ~1200 pt: 1e-6 pt, 0.35 nm)
    edge_tol_mm = 1e-6
    edges_x = np.array([x for x, _, w, _ in rects if w < size[0] * MM_TO_PT]) / MM_TO_PT
    assert np.max(np.abs(edges_x / cw - np.round(edges_x / cw))) * cw <= edge_tol_mm
    edges_y = np.array([size[1] * MM_TO_PT - y - h for _, y, w, h in rects if w >= size[0] * MM_TO_PT - 1e-6])
    edges_y = edges_y / MM_TO_PT
    assert edges_y.size and np.max(np.abs(edges_y / ch - np.round(edges_y / ch))) * ch <= edge_tol_mm


def test_svg_in_millimetres(tmp_path):
    out = tmp_path / "board.svg"
    write_pattern(PatternSpec(2.0, 297.0, 210.0), out)
    text = out.read_text()
    assert 'width="297mm" height="210mm" viewBox="0 0 297 210"' in text
    # one even-odd path of stripes: even columns 1 mm wide, full board height (210 - 25 mm margin)
    (path,) = re.findall(r'<path fill="black" fill-rule="evenodd"[^>]* d="([^"]+)"', text)
    stripes = [tuple(map(float, m)) for m in re.findall(r"M([\d.e-]+) ([\d.e-]+)h([\d.e-]+)v([\d.e-]+)", path)]
    columns = [s for s in stripes if s[3] == 185.0]
    rows = [s for s in stripes if s[2] == 297.0]
    assert len(columns) == 149 and len(rows) == 92 and len(stripes) == 241
    assert {w for _, _, w, _ in columns} == {1.0} and [x for x, *_ in columns[:3]] == [0.0, 2.0, 4.0]
    assert {h for *_, h in rows} == {1.0} and [y for _, y, *_ in rows[:3]] == [1.0, 3.0, 5.0]


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
                                   "pattern_stretch_y": s.stretch_y, "pattern_period_mm": s.period_stretched_mm})
    assert Geometry.from_toml_text(geometry.to_toml_text()) == geometry
    image, _ = forward.render(forward.FlatSurface(), geometry, (256, 256), stretched)
    carriers = find_carriers(image)
    f_row, f_col = np.abs(np.asarray(carriers.freq)).max(axis=0)
    assert 1 / f_col == pytest.approx(s.period_px_stretched[0], rel=0.01)
    assert 1 / f_row == pytest.approx(s.period_px_stretched[1], rel=0.01)
    # a square-board reading says the camera looks straight on; the stretch fixes it
    assert not abs(theta_from_carriers(carriers.freq) - theta) < 5
    assert theta_from_carriers(carriers.freq, s.stretch_y) == pytest.approx(theta, abs=0.5)
    alignment = Reconstructor(image, geometry).alignment(image)  # the board's period checked and accepted
    assert alignment["theta_estimate_deg"] == pytest.approx(theta, abs=0.5)
    assert geometry.board_period_mm(carriers.freq, image.shape) == pytest.approx(s.period_stretched_mm, rel=0.005)
    assert alignment["board_period_mm"] == pytest.approx(s.period_stretched_mm, rel=0.005)  # the Alignment tab's


#: Run by a small launcher process: caps its address space, forks the CLI and reports the
#: CLI's own peak RSS. Forked straight from pytest, the CLI's ru_maxrss would start at
#: pytest's RSS (Linux keeps the high-water mark of the memory a process had before exec:
#: 1.8 GB late in a full run, whatever the CLI did).
LAUNCHER = """
import os, resource, sys
limit, report = int(sys.argv[1]), sys.argv[2]
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
pid = os.fork()
if pid == 0:
    os.execv(sys.executable, [sys.executable, "-m", "app.cli", *sys.argv[3:]])
_, status, usage = os.wait4(pid, 0)
with open(report, "w") as f:
    f.write(f"{os.waitstatus_to_exitcode(status)} {usage.ru_maxrss}")
"""


def _cli_peak(*args, limit_bytes=3 * 1024**3):
    """Run the CLI in a subprocess whose address space is capped (a regression fails with a
    MemoryError instead of taking the machine), and return (exit code, stderr, peak RSS bytes,
    seconds) of that one process (os.wait4 in a small launcher: its own rusage only)."""
    import tempfile
    import threading
    import time

    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "peak.txt"
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(limit_bytes), str(report), *map(str, args)],
                                cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        watchdog = threading.Timer(300.0, proc.kill)  # hang detector, far above the ~2 s it takes
        watchdog.start()
        try:
            err = proc.stderr.read()
            proc.wait()
        finally:
            watchdog.cancel()
            proc.stderr.close()
        seconds = time.monotonic() - t0
        assert proc.returncode == 0 and report.exists(), f"the launcher failed ({proc.returncode}): {err}"
        code, maxrss_kib = (int(v) for v in report.read_text().split())
    return code, err, maxrss_kib * 1024, seconds


@pytest.mark.parametrize("period, size, suffix, says", [
    ("0.001", "200,200", ".pdf", "squares of 0.0005 mm, smaller than a printer can draw"),
    ("2", "10000,10000", ".pdf", "10000 x 9975 = 9.98e+07 squares"),
    ("2", "10000,10000", ".svg", "10000 x 9975 = 9.98e+07 squares"),
    ("2", "10000,10000", ".png", "10000 x 9975 = 9.98e+07 squares"),
    ("2", "2000,2000", ".png", "PNG at 600 dpi needs about 4.6 GB of memory"),
    ("2", "6000,300", ".pdf", "larger than a PDF page can be (5080 mm"),
])
def test_boards_beyond_what_the_output_can_hold_are_refused_in_bounded_memory(tmp_path, period, size,
                                                                             suffix, says):
    """issue 18: 0.001 mm on 200 x 200 mm was OOM-killed at 24 GB, 10 x 10 m reached 14 GB (PDF)
    or a 416 GiB traceback (PNG). Now: one line that says why and what to do, nothing written."""
    out = tmp_path / f"board{suffix}"
    code, err, peak, seconds = _cli_peak("pattern", "--period-mm", period, "--size-mm", size, "--out", out)
    assert code == 2, err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()
    assert peak < 500e6, f"peak memory {peak / 1e6:.0f} MB"


def test_large_vector_board_is_described_not_drawn(tmp_path):
    """A 1.2 x 5 m board (PDF) at 2 mm: 3 million squares in a file of a few kB, in bounded memory."""
    out = tmp_path / "big.pdf"
    code, err, peak, _ = _cli_peak("pattern", "--period-mm", "2", "--size-mm", "1200,5000", "--out", out)
    assert code == 0, err
    assert out.stat().st_size < 200_000 and peak < 500e6
    box, _, rects, _, fill_ops = _pdf_numbers(out)
    assert fill_ops == [b"f*"] and len(rects) == 600 + 2487  # 600 columns of 1200, 2487 odd rows of 4975


def test_png_memory_is_what_png_bytes_needed_says(tmp_path):
    """An A3 board at 600 dpi (70 Mpx): the child's peak stays within the estimate above the
    interpreter's own footprint, the estimate the refusal is based on."""
    from app.batch.pattern import png_bytes_needed

    out = tmp_path / "a3.png"
    code, err, peak, _ = _cli_peak("pattern", "--period-mm", "2", "--size-mm", "420,297", "--out", out)
    assert code == 0, err
    need = png_bytes_needed(PatternSpec(2.0, 420.0, 297.0), 600.0)
    _, _, base, _ = _cli_peak("pattern", "--period-mm", "2", "--size-mm", "420,297", "--out", tmp_path / "a.pdf")
    assert peak - base < 1.2 * need, (peak, base, need)


@pytest.mark.parametrize("distance_mm", [None, 1500.0, 800.0])
def test_suggest_knows_the_camera_distance_and_says_when_it_assumes_a_telecentric_lens(distance_mm):
    """By-hand trial of 7 Dec 2026 (F5): --suggest had no camera distance and promised 18.8 / 10.8 px where a
    camera 1500 mm away sees 13.9 / 8.0 px. With --camera-distance-mm the periods it states are the ones a
    ray-traced view of its board shows at the image centre; without it, it says it assumes a telecentric lens."""
    from processing import Geometry, forward
    from processing.carriers import find_carriers

    argv = ["pattern", "--suggest", "--theta-deg", "55", "--depth-mm", "300", "--pixel-mm", "0.08",
            "--camera", "256x256"] + ([] if distance_mm is None else ["--camera-distance-mm", distance_mm])
    r = _cli(*argv)
    assert r.returncode == 0, r.stderr
    assumes = "this suggestion assumes a telecentric lens (no --camera-distance-mm)"
    assert (assumes in r.stdout) == (distance_mm is None), r.stdout
    period_mm = float(re.search(r"suggested period: ([\d.]+) mm", r.stdout).group(1))
    px_x, px_y = (float(v) for v in re.search(r"square board: +([\d.]+) px per period along x \(columns\), "
                                              r"([\d.]+) px along y", r.stdout).groups())
    assert math.sqrt(px_x * px_y) == pytest.approx(14.0, rel=0.05)
    s = suggest_period(55.0, 300.0, 0.08, (256, 256), distance_mm)
    assert s.period_mm == period_mm
    geometry = Geometry.from_dict({"setup": "tir", "theta_deg": 55.0, "depth_mm": 300.0, "pixel_mm": 0.08,
                                   "rows_toward_camera": False,
                                   **({} if distance_mm is None else {"camera_distance_mm": distance_mm})})
    image, _ = forward.render(forward.FlatSurface(), geometry, (256, 256),
                              forward.Checkerboard(period_mm=period_mm, edge_softness_mm=0.08), supersample=3)
    f_row, f_col = np.abs(np.asarray(find_carriers(image).freq)).max(axis=0)
    assert 1 / f_col == pytest.approx(px_x, rel=0.02) and 1 / f_row == pytest.approx(px_y, rel=0.02)
    r = _cli(*argv[:-2], "--camera-distance-mm", "-5") if distance_mm else None
    assert r is None or (r.returncode == 2 and "--camera-distance-mm" in r.stderr)
