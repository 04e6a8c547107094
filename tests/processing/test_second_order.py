"""Second-order optics of the height solve (processing/second_order.py).

The linear model ``u = a h + B grad h`` leaves out two second-order terms (the
reflection's nonlinearity in the slope, the hit point's move with the
height): even the exact displacement of a deep dimple then gives heights
0.19 % off.  Exact ray tracing (processing.forward), never the linear model.
"""

import types

import numpy as np
import pytest

from benchmarks.bench_processing import rel_height_error
from processing import forward as F
from processing.dic_nodes import NodeGrid
from processing.geometry import Geometry
from processing.height import solver_for
from processing.reconstruct import Reconstructor
from processing.second_order import SECOND_ORDER_MIN_EFFECT, SecondOrderOptics

N = 256
G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
#: Telecentric either way round, and a camera at 1.5 m.
GEOMETRIES = [G55, Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=True),
              Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False, camera_distance_mm=1500.0)]
GEOMETRY_IDS = ["telecentric", "rows towards the camera", "camera at 1.5 m"]


def _node_grid_error(geometry, surface):
    """``(first-order error %, second-order error %)`` of the heights of ``surface``'s exact displacement
    on image matching's node grid of a 256^2 frame."""
    ng = NodeGrid((N, N))
    hs = solver_for(geometry, ng.rows_px, ng.cols_px, (N, N))
    second = SecondOrderOptics(geometry, ng.rows_px, ng.cols_px, (N, N), hs.x_mm, hs.y_mm)
    u = F.true_displacement(surface, geometry, (N, N), rows_px=ng.rows_px, cols_px=ng.cols_px)[0]
    valid = np.ones(ng.shape, bool)
    h1 = np.asarray(hs.solve(u.astype(np.float32), valid).height_mm)
    h2 = np.asarray(hs.solve(second.corrected_displacement(u, h1, valid), valid).height_mm)

    def error(h):
        res = types.SimpleNamespace(carriers=types.SimpleNamespace(shape=(N, N)), rows_px=ng.rows_px,
                                    cols_px=ng.cols_px, valid=valid, x_mm=hs.x_mm, y_mm=hs.y_mm, height=h)
        return rel_height_error(res, surface, geometry)

    return error(h1), error(h2), second.effect(h1, valid)


@pytest.mark.parametrize("geometry", GEOMETRIES, ids=GEOMETRY_IDS)
def test_the_exact_displacement_of_a_deep_dimple_gives_its_heights_to_second_order(geometry):
    """15 um deep, sigma 9 mm (the accuracy table's deep dimple): first order 0.12-0.19 % off, with the two
    second-order terms taken off at most a tenth of that (measured 0.002-0.004 %)."""
    first, second, effect = _node_grid_error(geometry, F.Dimple(0.015, 9.0))
    assert first > 0.1 and second < 0.1 * first, (first, second)
    assert effect >= SECOND_ORDER_MIN_EFFECT  # the chains would correct it


def test_small_slopes_are_left_to_the_linear_model():
    """The accuracy table's waves (1 um rms, 12-30 mm; 0.3 um rms, 6-12 mm) stay under the threshold: their
    floor (0.10 and 0.21 % here) is not where their error is, and a correction computed from their heights
    moved the table by -0.04 to +0.03 points (errors that had cancelled part of the floor)."""
    for surface in (F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=3),
                    F.WaveField.random(8, amplitude_rms_mm=0.0003, wavelength_range_mm=(6, 12), seed=1)):
        first, second, effect = _node_grid_error(G55, surface)
        assert effect < SECOND_ORDER_MIN_EFFECT
        assert second < first  # what the correction would do there: the floor itself goes


@pytest.mark.parametrize("layers, camera_mm, amplitude_mm, first_min, second_max", [
    (((10.0, 1.333),), None, 1.1, 3.0, 0.05),
    (((5.0, 1.333),), 300.0, 2.2, 12.0, 0.6),
], ids=["1.1 mm on 10 mm, telecentric", "2.2 mm on 5 mm, camera at 300 mm"])
def test_fsss_heights_tall_against_the_water_depth_are_corrected(layers, camera_mm, amplitude_mm, first_min,
                                                                  second_max):
    """By-hand sweep of 7 Dec 2026: FS-SS over shallow water, heights a tenth of the depth and more (the
    column under a raised surface is taller, the refraction bends with the slope's square): ``simulate``'s
    bump came out 3.6 % and 14.4 % off, exit 0, no word.  The exact displacement of such a bump (sigma 3 mm)
    gives heights 3.8 / 15.2 % off to first order; corrected from each solve's heights in turn (FS-SS
    passes, ``solved_again``), 0.02 / 0.41 %."""
    from processing.second_order import solved_again

    geometry = Geometry(setup="fsss", pixel_mm=0.1, fsss_layers=layers, fsss_camera_distance_mm=camera_mm)
    surface = F.GaussianBump(amplitude_mm, 3.0)
    ng = NodeGrid((N, N))
    hs = solver_for(geometry, ng.rows_px, ng.cols_px, (N, N))
    second = SecondOrderOptics(geometry, ng.rows_px, ng.cols_px, (N, N), hs.x_mm, hs.y_mm)
    u = F.true_displacement(surface, geometry, (N, N), rows_px=ng.rows_px, cols_px=ng.cols_px)[0]
    valid = np.ones(ng.shape, bool)
    truth = F.true_height(surface, geometry, (N, N), rows_px=ng.rows_px, cols_px=ng.cols_px)

    def error(h):  # rel. RMS %, the constant (FS-SS's null space) taken out of both
        d = np.asarray(h, np.float64) - truth
        return 100 * float(np.std(d) / np.std(truth))

    h1 = np.asarray(hs.solve(u.astype(np.float32), valid).height_mm)
    timings = {}
    again = solved_again(second, u, h1, valid, lambda u2: hs.solve(u2, valid), timings)
    assert error(h1) > first_min and again is not None and "second_order" in timings
    assert error(np.asarray(again.height_mm)) < second_max, (error(h1), error(np.asarray(again.height_mm)))


def test_fsss_heights_small_against_the_depth_are_left_to_the_linear_model():
    """The lab's stack (57 mm of air, 12 of glass, 43 of water) and a 50 um bump: effect 4e-4, under the
    threshold; nothing is solved again (the linear heights are within 0.013 % there)."""
    fsss = Geometry(setup="fsss", pixel_mm=0.2, fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)),
                    n_water=1.34)
    ng = NodeGrid((64, 64))
    hs = solver_for(fsss, ng.rows_px, ng.cols_px, (64, 64))
    second = SecondOrderOptics(fsss, ng.rows_px, ng.cols_px, (64, 64), hs.x_mm, hs.y_mm)
    surface = F.GaussianBump(0.05, 3.0)
    u = F.true_displacement(surface, fsss, (64, 64), rows_px=ng.rows_px, cols_px=ng.cols_px)[0]
    valid = np.ones(ng.shape, bool)
    h1 = np.asarray(hs.solve(u.astype(np.float32), valid).height_mm)
    assert 0.0 < second.effect(h1, valid) < SECOND_ORDER_MIN_EFFECT


def test_the_default_reconstruction_of_a_deep_dimple_is_corrected():
    """Ray-traced frames, 8 bit: ``Reconstructor(reference, geometry)(frame)`` (image matching on the full
    grid) of the deep dimple with the correction: 0.179 -> 0.028 % (4 x 4 rays a pixel); a small bump's
    frame (1 um, below the threshold) takes no second solve."""
    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    ref, _ = F.render_tir(F.FlatSurface(), G55, (N, N), board, supersample=2)
    rng = np.random.default_rng(0)
    ref8 = F.quantize(ref, bits=8, rng=rng)
    rec = Reconstructor(ref8, G55)
    deep = F.Dimple(0.015, 9.0)
    img, _ = F.render_tir(deep, G55, (N, N), board, supersample=2)
    res = rec(F.quantize(img, bits=8, rng=rng))
    assert "second_order" in res.timings_ms and not res.note
    assert rel_height_error(res, deep) < 0.1
    small = F.GaussianBump(0.001, 5.0)
    img, _ = F.render_tir(small, G55, (N, N), board, supersample=2)
    rec.reset_series()
    res = rec(F.quantize(img, bits=8, rng=rng))
    assert "second_order" not in res.timings_ms


def test_what_is_taken_off_is_second_order_in_the_heights():
    """The reflection's nonlinear part ``N(h)`` (the trace of the local planes less the height solver's own
    linear response) scales with the square of the heights: doubled heights give four times it, to within
    the third-order terms (a linear residue from a linear part that is not the trace's would double
    instead: one 1 % off fails this). And it is small: 6e-3 px against a 5 px displacement for the deep
    dimple."""
    ng = NodeGrid((N, N))
    for geometry in (G55, Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False,
                                   camera_distance_mm=1500.0)):
        hs = solver_for(geometry, ng.rows_px, ng.cols_px, (N, N))
        second = SecondOrderOptics(geometry, ng.rows_px, ng.cols_px, (N, N), hs.x_mm, hs.y_mm)
        h = F.true_height(F.Dimple(0.015, 9.0), geometry, (N, N), rows_px=ng.rows_px, cols_px=ng.cols_px)
        valid = np.ones(ng.shape, bool)
        n1 = second.nonlinear_part(h, valid)
        n2 = second.nonlinear_part(2.0 * h, valid)
        size = float(np.sqrt(np.mean(n1 ** 2)))
        assert 1e-4 < size < 1e-2, size
        assert np.sqrt(np.mean((n2 - 4.0 * n1) ** 2)) < 0.05 * 4.0 * size


@pytest.mark.parametrize("geometry", GEOMETRIES, ids=GEOMETRY_IDS)
def test_the_compiled_trace_of_the_local_planes_is_the_tracers_to_the_bit(geometry):
    """The correction's trace (processing.trace_kernels, 6 of the 15 ms of a 1024^2 default frame's correction in
    NumPy) against processing.forward.trace_tir of the same planes: every pattern point and lost ray the same bits,
    on slopes from still water to ones where TIR is lost."""
    from processing.second_order import _LocalPlanes

    rng = np.random.default_rng(3)
    rows = cols = np.linspace(0.0, N - 1.0, 64)
    optics = SecondOrderOptics(geometry, rows, cols, (N, N), None, None)
    shape = optics.rows.shape
    for slope in (0.0, 1e-4, 0.05, 0.6):
        h = rng.normal(0.0, 0.01, shape)
        gx, gy = rng.normal(0.0, slope, shape), rng.normal(0.0, slope, shape)
        pat, lost, _, _, _ = F.trace_tir(_LocalPlanes(h, gx, gy, optics.x0, optics.y0), geometry, optics.rows,
                                         optics.cols, (N, N), rays=optics._rays)
        pat_x, pat_y, lost_k = optics._trace_tir(h, gx, gy)
        np.testing.assert_array_equal(pat_x, pat[..., 0])
        np.testing.assert_array_equal(pat_y, pat[..., 1])
        np.testing.assert_array_equal(lost_k, lost)
        if slope == 0.6:
            assert lost.any() and not lost.all()  # the steep case does reach rays beyond TIR
