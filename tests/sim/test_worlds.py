"""World sources: procedural town, Lanelet2 (Karlsruhe) and Argoverse 2 importers, repaint."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from common.classes import Cls
from common.errors import WorldError
from common.geometry import latlon_to_local_m
from services.sim import paint
from services.sim.town import build_town
from services.sim.worlds import load_world, repaint


def _classes_along(world, pts):
    x0, y0, _, _ = world.bounds(5.0)
    r = world.rasterize(
        x0, y0, int((world.bounds()[3] - y0) / 0.1) + 60, int((world.bounds()[2] - x0) / 0.1) + 60
    )
    c = ((pts[:, 0] - x0) / 0.1).astype(int)
    rr = ((pts[:, 1] - y0) / 0.1).astype(int)
    return r[rr, c]


def test_town_is_seeded_and_has_every_marking_kind():
    a, b = load_world("town:1", seed=4), load_world("town:1", seed=4)
    assert len(a.markings) == len(b.markings)
    assert all(
        np.array_equal(m.polygon_xy_m, n.polygon_xy_m)
        for m, n in zip(a.markings, b.markings, strict=False)
    )
    kinds = {(m.cls, m.kind) for m in a.markings}
    for need in [
        (Cls.LANE_LINE, "dashed"),
        (Cls.LANE_LINE, "solid"),
        (Cls.LANE_LINE, "double"),
        (Cls.STOP_LINE, "stop"),
        (Cls.CROSSWALK, "zebra"),
        (Cls.ROAD, "road"),
    ]:
        assert need in kinds
    assert any(m.cls == Cls.GROUND_SIGN and m.kind.startswith("arrow") for m in a.markings)
    assert (
        load_world("town:1", seed=5).markings[0].polygon_xy_m.tolist()
        != a.markings[0].polygon_xy_m.tolist()
    )


@pytest.mark.parametrize("km", [1.0, 2.0, 4.0])
def test_town_size_in_km_of_road(km):
    world = load_world(f"town:{km}")
    assert 0.7 * km <= world.km_of_road <= 1.3 * km


def test_town_routes_run_on_the_road_and_cross_a_300m_gnss_outage():
    world = load_world("town", seed=0)
    route = paint.resample(world.routes[0], 2.0)
    on_road = _classes_along(world, route) >= Cls.ROAD
    assert on_road.mean() > 0.97
    blocked = world.gnss_blocked_at(route)
    assert blocked.sum() * 2.0 >= 300.0
    assert not blocked[:50].any()  # a drive starts with a fix


def test_wide_town_roads_have_their_lanes_a_raised_median_and_routes_on_every_lane():
    """Training towns (training.data.LANE_MIX): four lanes each way split by a median."""
    world = build_town(1.0, seed=3, lane_mix=(0.0, 0.0, 0.0, 1.0), median_prob=1.0)
    assert len(world.routes) == 5  # lanes 0 and 1 as the default town, and lanes 2 and 3
    # across the road from the innermost lane's route, mid-block: to the left the median
    # (none) between two lines, to the right three and a half lanes of road
    route = paint.resample(world.routes[0], 2.0)
    left = paint.normals(route)
    steps = np.arange(0.0, 14.0, 0.1)
    across = route[:, None, :] + steps[None, :, None] * left[:, None, :]  # to the left
    back = route[:, None, :] - steps[None, :, None] * left[:, None, :]  # to the right
    both = _classes_along(world, np.concatenate([across, back]).reshape(-1, 2))
    to_left, to_right = both.reshape(2, len(route), len(steps))
    mid_block = [row[:60] for row in to_left if set(row[:60]) <= {0, Cls.ROAD, Cls.LANE_LINE}]
    assert len(mid_block) > 0.4 * len(route)  # junctions and crosswalks aside

    def median_between_lines(row):
        if not (row == 0).any():
            return False
        first_none = int(np.argmax(row == 0))
        return Cls.LANE_LINE in row[:first_none] and Cls.LANE_LINE in row[first_none:]

    assert np.mean([median_between_lines(row) for row in mid_block]) > 0.6
    widths = [int(np.argmax(row == 0)) * 0.1 for row in to_right if (row == 0).any()]
    assert np.median(widths) >= 3.5 * 3.0 - 0.2
    on_road = _classes_along(world, np.concatenate([paint.resample(r, 2.0)
                                                    for r in world.routes])) >= Cls.ROAD
    assert on_road.mean() > 0.97


def test_wide_roads_are_opt_in():
    """The default town (demo, tests) keeps one lane each way, two on its arterial row."""
    world = load_world("town:1", seed=4)
    assert len(world.routes) == 3
    roads = [m for m in world.markings if m.cls == Cls.ROAD and m.kind == "road"]
    wide = build_town(1.0, seed=4, lane_mix=(0.0, 0.0, 0.0, 1.0), median_prob=1.0)
    assert len([m for m in wide.markings if m.cls == Cls.ROAD and m.kind == "road"]) == \
        2 * len(roads)  # every road split in two carriageways


def test_repaint_moves_one_line_about_a_metre():
    world = load_world("town:1", seed=2)
    after = repaint(world, seed=1)
    moved = [(m, n) for m, n in zip(world.markings, after.markings, strict=False) if m is not n]
    assert moved and all(m.cls == Cls.LANE_LINE for m, _ in moved)
    shifts = [np.linalg.norm(n.polygon_xy_m.mean(0) - m.polygon_xy_m.mean(0)) for m, n in moved]
    assert np.allclose(shifts, 1.0)
    # the repainted line is on the first 400 m of the first route (short drives see it)
    s = paint.arc_length(world.routes[0])
    near = world.routes[0][s < 400.0]
    d = np.min(np.linalg.norm(near[:, None] - moved[0][0].polygon_xy_m.mean(0), axis=2))
    assert d < 12.0


def test_unknown_world_spec_is_a_world_error():
    with pytest.raises(WorldError):
        load_world("mars")
    with pytest.raises(WorldError):
        load_world("lanelet2:/nonexistent.osm")


# -- real maps ---------------------------------------------------------------------------------


def _osm_ways(path, typ):
    root = ET.parse(path).getroot()
    nodes = {n.get("id"): (float(n.get("lat")), float(n.get("lon"))) for n in root.iter("node")}
    for w in root.iter("way"):
        tags = {t.get("k"): t.get("v") for t in w.findall("tag")}
        if tags.get("type") == typ:
            yield np.array([nodes[n.get("ref")] for n in w.findall("nd")])


@pytest.fixture(scope="module")
def karlsruhe(shared_data):
    path = shared_data / "lanelet2-karlsruhe" / "mapping_example.osm"
    return path, load_world(f"lanelet2:{path}")


def test_karlsruhe_markings_are_where_the_osm_puts_them(karlsruhe):
    path, world = karlsruhe
    lat0, lon0 = world.origin_latlon
    idx = {c: [m for m in world.markings if m.cls == c] for c in Cls}
    assert len(idx[Cls.STOP_LINE]) == 28
    assert len(idx[Cls.CROSSWALK]) > 100 and len(idx[Cls.LANE_LINE]) > 300
    for typ, cls in (("stop_line", Cls.STOP_LINE), ("line_thick", Cls.LANE_LINE)):
        hits = []
        for ll in list(_osm_ways(path, typ))[:12]:
            x, y = latlon_to_local_m(ll[:, 0], ll[:, 1], lat0, lon0)
            pts = paint.resample(np.stack([x, y], axis=1), 0.5)
            lo = pts.min(axis=0) - 2.0
            hi = pts.max(axis=0) + 2.0
            r = world.rasterize(
                lo[0], lo[1], int((hi[1] - lo[1]) / 0.1), int((hi[0] - lo[0]) / 0.1)
            )
            cells = ((pts - lo) / 0.1).astype(int)
            hits.append(np.mean(r[cells[:, 1], cells[:, 0]] == cls))
        # stop lines are solid; line_thick ways are solid or dashed (3 m of every 9 m)
        assert np.median(hits) > (0.9 if typ == "stop_line" else 0.3), (typ, hits)


def test_karlsruhe_km_of_road_and_routes(karlsruhe):
    _, world = karlsruhe
    assert 1.5 <= world.km_of_road <= 4.0  # 3.4 km x 1 km map, ~6 km of directed lanelets
    assert paint.arc_length(world.routes[0])[-1] > 500.0
    assert world.gnss_blocked


def test_dashed_lines_are_drawn_as_dashes(karlsruhe):
    _, world = karlsruhe
    dashes = [m for m in world.markings if m.kind == "dashed"]
    lengths = [paint.arc_length(m.polygon_xy_m[: len(m.polygon_xy_m) // 2])[-1] for m in dashes]
    assert np.median(lengths) == pytest.approx(3.0, abs=0.1)


def test_av2_logs_import_with_real_ego_route(shared_data):
    logs = sorted(p for p in (shared_data / "av2").iterdir() if p.is_dir())
    assert logs
    for log in logs:
        world = load_world(f"av2:{log}")
        length = paint.arc_length(world.routes[0])[-1]
        assert 30.0 < length < 120.0
        cls = {m.cls for m in world.markings}
        assert {Cls.ROAD, Cls.LANE_LINE, Cls.CROSSWALK} <= cls
        # the ego vehicle drives on the drivable area
        on = _classes_along(world, paint.resample(world.routes[0], 1.0)) >= Cls.ROAD
        assert on.mean() > 0.9


def test_av2_camera_is_a_real_front_camera(shared_data):
    from services.sim.av2 import av2_camera

    log = shared_data / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
    cam = av2_camera(log, scale=0.25)
    assert (cam.width, cam.height) == (388, 512)  # portrait ring_front_center, quarter size
    assert 1.3 < cam.T_vehicle_camera[2, 3] < 1.5
    uv, front = cam.project_vehicle_points(np.array([[30.0, 0.0, cam.T_vehicle_camera[2, 3]]]))
    assert front[0] and abs(uv[0, 0] - cam.K[0, 2]) < 5 and abs(uv[0, 1] - cam.K[1, 2]) < 5
