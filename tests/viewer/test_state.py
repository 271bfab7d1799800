"""The viewer's core and HTTP server without a browser or a fleet: tile PNGs in the map palette,
north up; newest versions win; poses age; the packaged page and its API over real HTTP."""

import json
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from common.classes import COLORS_RGB, Cls
from common.contours import encode_tile
from common.messages import Pose, Tile
from services.viewer.server import serve, static_file
from services.viewer.state import POSE_STALE_S, ViewerState
from tests.merger.helpers import lane_tile


class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def _tile(version: int, labels=None) -> Tile:
    return Tile(tile=(2, -1), version=version, codec="contour/2",
                data=encode_tile(lane_tile() if labels is None else labels))


def test_png_is_the_tile_in_the_palette_north_up():
    state = ViewerState("test")
    state.put_tile(_tile(1))
    img = cv2.imdecode(np.frombuffer(state.png((2, -1)), np.uint8), cv2.IMREAD_UNCHANGED)
    rgba = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    labels = lane_tile()
    assert rgba.shape == (512, 512, 4)
    # image row 0 is the tile's north edge (row 511)
    assert np.array_equal(rgba[511 - 301, 180, :3], COLORS_RGB[Cls.STOP_LINE])
    assert labels[301, 180] == Cls.STOP_LINE
    assert np.array_equal(rgba[511 - 10, 200, :3], COLORS_RGB[Cls.LANE_LINE])
    assert rgba[0, 10, 3] == 0 and rgba[0, 170, 3] == 255  # no data: transparent


def test_newer_versions_win_and_poses_go_stale():
    clock = _Clock()
    state = ViewerState("test", clock=clock)
    assert state.put_tile(_tile(3)) and not state.put_tile(_tile(2)) and state.put_tile(_tile(4))
    state.put_pose(Pose("car", 1, 1.0, 2.0, 0.5, np.eye(3) * 0.04, True))
    snap = state.snapshot()
    assert snap["tiles"] == [{"tx": 2, "ty": -1, "version": 4, "shard": None}]
    assert snap["poses"][0]["sigma_m"] == pytest.approx(0.2) and not snap["poses"][0]["stale"]
    clock.t += POSE_STALE_S + 1
    assert state.snapshot()["poses"][0]["stale"]


def test_page_and_api_over_http():
    state = ViewerState("test")
    state.put_tile(_tile(5), shard="s1")
    state.put_stats({"s1": {"patches_applied": 9, "tile_list": "2,-1"}}, {(2, -1): "s1"})
    httpd = serve(state, "127.0.0.1", 0)
    base = f"http://127.0.0.1:{httpd.server_address[1]}"
    try:
        page = urllib.request.urlopen(base + "/").read()
        assert page == static_file("index.html") and b"/static/app.js" in page
        for name in ("app.js", "style.css"):
            assert urllib.request.urlopen(f"{base}/static/{name}").read() == static_file(name)
        snap = json.loads(urllib.request.urlopen(base + "/api/state").read())
        assert snap["tiles"][0]["shard"] == "s1" and "tile_list" not in snap["shards"]["s1"]
        info = json.loads(urllib.request.urlopen(base + "/api/tile/2/-1").read())
        assert info["version"] == 5 and info["shard_stats"] == {"patches_applied": 9}
        png = urllib.request.urlopen(base + "/api/tile/2/-1.png")
        assert png.headers["Content-Type"] == "image/png" and png.read() == state.png((2, -1))
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(base + "/api/tile/0/0.png")
        assert err.value.code == 404
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(base + "/static/../state.py")
    finally:
        httpd.shutdown()
        httpd.server_close()
