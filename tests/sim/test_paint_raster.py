"""Paint geometry and rasterization against known geometry (0.1 m cells)."""

import numpy as np

from common.classes import Cls
from common.world import Marking, World
from services.sim import paint
from services.sim.raster import MarkingIndex, TileCache
from services.sim.worlds import load_world


def _raster(markings, x0=-1.0, y0=-2.0, rows=40, cols=140):
    return World("t", markings).rasterize(x0, y0, rows, cols)


def test_stop_line_rectangle_covers_exact_cells():
    m = paint.stop_line(np.array([0.0, 0.0]), np.array([0.0, 1.0]))  # 0.3 m wide, 1 m long
    r = _raster([m])
    # cv2.fillPoly rounds vertices to cell centres and fills inclusively: up to one extra cell
    rows, cols = np.nonzero(r == Cls.STOP_LINE)
    assert 10 <= np.ptp(rows) + 1 <= 11 and 3 <= np.ptp(cols) + 1 <= 4


def test_dashed_line_has_real_dash_and_gap():
    line = np.array([[0.0, 0.0], [12.0, 0.0]])
    dashes = paint.line_markings(line, "dashed", paint.LINE_THIN_M, 3.0, 6.0)
    assert len(dashes) == 2  # [0, 3] and [9, 12]
    spans = sorted((d.polygon_xy_m[:, 0].min(), d.polygon_xy_m[:, 0].max()) for d in dashes)
    assert np.allclose(spans, [(0.0, 3.0), (9.0, 12.0)])
    widths = [np.ptp(d.polygon_xy_m[:, 1]) for d in dashes]
    assert np.allclose(widths, paint.LINE_THIN_M)
    r = _raster(dashes)
    cols = np.flatnonzero((r == Cls.LANE_LINE).any(axis=0))
    assert 60 <= len(cols) <= 62  # 2 dashes x 3 m at 0.1 m (+1 cell each, fillPoly)


def test_double_line_is_two_strips_with_a_gap():
    polys = paint.line_polygons(np.array([[0.0, 0.0], [5.0, 0.0]]), "double", 0.12)
    ys = sorted(p[:, 1].mean() for p in polys)
    assert len(polys) == 2 and abs(ys[1] - ys[0] - 0.24) < 1e-9


def test_zebra_stripes_are_half_metre():
    left = np.array([[0.0, 2.0], [6.0, 2.0]])
    right = np.array([[0.0, -2.0], [6.0, -2.0]])
    stripes = paint.zebra(left, right)
    assert len(stripes) == 6
    lengths = [np.ptp(s.polygon_xy_m[:, 0]) for s in stripes]
    assert np.allclose(lengths, 0.5)
    assert all(s.cls == Cls.CROSSWALK for s in stripes)


def test_overlapping_polygons_do_not_cancel():
    a = Marking(Cls.ROAD, np.array([[0, 0], [4, 0], [4, 2], [0, 2]], float))
    b = Marking(Cls.ROAD, np.array([[2, 0], [6, 0], [6, 2], [2, 2]], float))
    r = _raster([a, b])
    assert (r[20:40, 10:70] == Cls.ROAD).all()  # the union, no even-odd hole in the overlap


def test_marking_index_matches_world_rasterize():
    world = load_world("town:1", seed=3)
    x0, y0 = world.routes[0][50] - 25.0
    ref = world.rasterize(x0, y0, 500, 500)
    assert np.array_equal(MarkingIndex(world).rasterize(x0, y0, 500, 500), ref)
    assert (ref >= Cls.LANE_LINE).any()


def test_tile_window_is_aligned_with_world_frame():
    world = load_world("town:1", seed=3)
    cache = TileCache(world, radius_tiles=1)
    x, y = world.routes[0][80]
    win, x0, y0 = cache.window(x, y)
    ref = world.rasterize(x0, y0, win.shape[0], win.shape[1])
    assert np.mean(win != ref) < 1e-3  # only sub-cell rounding at polygon edges differs
