"""services/demo/spread.py: the demo fleet's extra route and the shard_map that gives every
shard of the demo a region its drives touch."""

from collections import Counter

import numpy as np

from common.grid import REGION_TILES, TILE_M, owner_of_tile
from services.demo.spread import route_regions, spread_route, spread_shard_map

REGION_M = REGION_TILES * TILE_M  # 409.6 m


def _line(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y1]], float)


def test_route_regions_counts_only_the_driven_length():
    route = _line(10.0, 10.0, 10.0 + 2 * REGION_M, 10.0)
    assert route_regions(route, max_km=0.3) == {(0, 0)}
    assert route_regions(route, max_km=0.6) == {(0, 0), (1, 0)}


def test_spread_route_prefers_the_route_reaching_most_new_regions():
    shared = _line(10.0, 10.0, 300.0, 10.0)  # region (0, 0) only
    same = _line(20.0, 20.0, 310.0, 20.0)
    across = _line(350.0, 10.0, 350.0 + 0.5 * REGION_M, 10.0)  # (0, 0) into (1, 0)
    assert spread_route([shared, same, across], max_km=0.4) == 2
    assert spread_route([shared, same], max_km=0.4) is None
    assert spread_route([], max_km=0.4) is None


def test_spread_shard_map_gives_every_shard_a_region_heaviest_first():
    weights = Counter({(-4, -1): 1300, (-3, 0): 260, (-2, 0): 250, (-3, 1): 100})
    shard_map = spread_shard_map(weights, shards=2)
    assert shard_map["-4,-1"] == 0 and set(shard_map.values()) == {0, 1}
    assert all(shard_map[k] == 1 for k in ("-3,0", "-2,0", "-3,1"))  # the lighter shard fills
    three = spread_shard_map(weights, shards=3)
    assert set(three.values()) == {0, 1, 2}
    # the map is what every process reads: owner_of_tile follows it
    assert owner_of_tile((-4 * REGION_TILES, -1 * REGION_TILES), 2, shard_map) == 0
    assert owner_of_tile((-3 * REGION_TILES, 0), 2, shard_map) == 1
