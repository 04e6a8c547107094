"""Messages of processing/ found by the by-hand trials of 7 Dec 2026."""

import numpy as np

from processing import forward as F
from processing.geometry import Geometry
from processing.reconstruct import Reconstructor

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
BOARD = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)


def _reference(n=128):
    ref, _ = F.render_tir(F.FlatSurface(), G55, (n, n), BOARD)
    return F.quantize(ref, bits=8)


def test_a_reference_valid_area_too_small_to_measure_on_is_named_not_the_frames_contrast():
    ref = _reference()
    chain = Reconstructor(ref, G55).chain
    few = np.zeros_like(chain.reference_valid)
    few[3:5, 3:5] = True  # 4 samples: none is left once the edges are trimmed
    chain.reference_valid = few
    amplitude = np.ones(few.shape, np.float32)  # the frame's contrast is the reference's
    msg = str(chain.nothing_measured(ref, amplitude))
    assert "reference shows the pattern on only 4 of the" in msg
    assert "too small for this frame and board" in msg and "ten board periods" in msg
    assert "contrast" not in msg and "focus" not in msg


def test_a_view_many_depths_long_is_refused_with_the_values_that_make_it():
    import pytest

    from processing.errors import GeometryError

    G55.check_frame((1024, 1024))  # 179 mm of rows at 300 mm: T L / H = 0.28
    Geometry(theta_deg=55, depth_mm=20, pixel_mm=0.1, rows_toward_camera=False).check_frame((2048, 2048))
    shallow = Geometry(theta_deg=55, depth_mm=0.3, pixel_mm=0.1, rows_toward_camera=False)
    with pytest.raises(GeometryError, match=r"rows span 44.63 mm of surface \(pixel_mm = 0.1\), 149 times "
                                            r"depth_mm = 0.3, a view no TIR set-up has") as err:
        shallow.check_frame((256, 256))
    assert "check pixel_mm" in str(err.value) and "at most 10.22 mm" in str(err.value)


BASE = dict(setup="tir", theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=False)


def test_numpy_scalars_are_numbers_and_bools_are_not():
    import pytest

    from processing.errors import GeometryError

    g = Geometry(**{**BASE, "theta_deg": np.float32(55.0), "depth_mm": np.int64(300)})
    assert g.theta_deg == 55.0 and type(g.depth_mm) is float
    for bad in (True, np.bool_(True)):
        with pytest.raises(GeometryError, match="depth_mm must be a number of millimetres"):
            Geometry(**{**BASE, "depth_mm": bad})


def test_the_reconstructor_takes_a_geometry_its_dict_or_its_file_and_says_what_else_it_needs(tmp_path):
    import pytest

    ref = _reference()
    path = tmp_path / "g.toml"
    path.write_text(Geometry(**BASE).to_toml_text())
    for geometry in (BASE, str(path), path):
        assert Reconstructor(ref, geometry).geometry == Geometry(**BASE)
    with pytest.raises(TypeError, match="geometry must be a processing.Geometry, a dict of its keys or the path"):
        Reconstructor(ref, 55.0)
    with pytest.raises(TypeError, match=r"reference image must be an image array .*got the path 'ref.png'; "
                                        r"read it first, e.g. app.files.imageio.read_image\(path\)"):
        Reconstructor("ref.png", G55)
    with pytest.raises(TypeError, match="frame must be an image array"):
        Reconstructor(ref, G55)(tmp_path / "frame.png")


def test_a_geometry_file_with_a_byte_order_mark_or_other_tables_is_read_or_named(tmp_path):
    import pytest

    from processing.errors import GeometryError

    text = Geometry(**BASE).to_toml_text()
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert Geometry.from_toml(tmp_path / "bom.toml") == Geometry(**BASE)
    (tmp_path / "tables.toml").write_text("[geometry]\n" + text + "\n[notes]\nwho = \"me\"\n")
    with pytest.raises(GeometryError, match=r"holds a \[geometry\] table and also notes; a geometry file is its "
                                            r"keys either at the top of the file or in one \[geometry\] table"):
        Geometry.from_toml(tmp_path / "tables.toml")
    (tmp_path / "one.toml").write_text("[geometry]\n" + text)
    assert Geometry.from_toml(tmp_path / "one.toml") == Geometry(**BASE)


def test_the_readme_names_the_errors_a_script_meets_where_process_stores_a_status():
    # trial of 7 Dec 2026: the README's snippet said "NaN where invalid", and a black frame raised NoCarrierError
    import re
    from pathlib import Path

    from processing import errors
    from processing.errors import TirdeflectError

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    text = readme[readme.index("Scripting (the stable public interface)"):readme.index("Geometry (TOML, lengths")]
    assert "processing.errors" in text and "frame_status" in text and "catches `TirdeflectError`" in text
    named = set(re.findall(r"`(\w+Error)`", text)) - {"ValueError"}
    assert {"NoCarrierError", "PatternMismatchError", "AllInvalidError"} <= named
    assert all(issubclass(getattr(errors, name), TirdeflectError) for name in named)
    ref = _reference()
    try:
        Reconstructor(ref, G55)(np.zeros_like(ref))
    except TirdeflectError as exc:
        assert type(exc).__name__ in named
    else:
        raise AssertionError("a black frame was measured")
