"""The viewer end to end in a real browser: a real router, a `roadmap merger` shard and a
`roadmap viewer` process; the test ingests patches as a vehicle does and publishes a pose as a
localizer does, and Debian's headless Chromium (driven by Selenium through chromedriver) loads
the page. Checked on the screenshots: the map's marking cells are drawn in their class colours
where they are, a later patch shows up, the pose is drawn; a click shows the tile's version and
its shard's stats; the buttons and a drag zoom and pan. The screenshots are kept in
tests/artifacts/viewer/ (or $ROADMAP_TEST_ARTIFACTS/viewer)."""

import os
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from common import codec, keys
from common.bus import free_tcp_port, open_session
from common.classes import COLORS_RGB, Cls
from common.config import BusConfig
from common.contours import decode_tile
from common.messages import IngestBatch, Pose
from services import fleet as fleet_queries
from tests import fleet
from tests.conftest import REPO
from tests.merger.helpers import lane_tile, patches_from_labels

pytestmark = pytest.mark.integration

ARTIFACTS = Path(os.environ.get("ROADMAP_TEST_ARTIFACTS", REPO / "tests" / "artifacts")) / "viewer"
SCALE = 20.0  # pixels per metre: one 0.1 m cell = 2 x 2 pixels
CENTRE = (22.0, 28.0)  # view centre (m): the lane lines, the stop line and the crosswalk
POSE_XY = (27.0, 22.0)
POSE_RGB = (48, 209, 88)  # app.js POSE_OK
NEW_LINE_COLS = (260, 262)  # the line the later patches add


def _chrome():
    """A headless Chromium driven by chromedriver, or a skip saying what is missing."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium (.[test])")
    from selenium.webdriver.chrome.service import Service

    browser = next((shutil.which(b) for b in ("chromium", "chromium-browser") if shutil.which(b)),
                   None)
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("needs Debian's chromium and chromium-driver (.ci/run installs them: "
                    "apt-get install chromium chromium-driver)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1100,800", "--force-device-scale-factor=1",
                "--disable-background-networking", "--no-first-run"):
        opts.add_argument(arg)
    return webdriver.Chrome(service=Service(driver), options=opts)


@pytest.fixture
def live_viewer(router, tmp_path):
    """Router + shard s0 + viewer; yields (page URL, test session). The viewer lists the
    shards' tiles once a minute only: what the page shows after that came by tile-update."""
    port = free_tcp_port()
    shard = fleet.start_merger(router, tmp_path / "s0.sqlite", tmp_path / "merger.log")
    viewer = fleet.start("viewer", "--port", port, "--connect", router, "--stats-every", "60",
                         log=tmp_path / "viewer.log")
    url = f"http://127.0.0.1:{port}/"
    try:
        with open_session(BusConfig(connect=[router])) as session:
            fleet.wait_alive(session, "merger", "s0")
            fleet.wait_http(url + "api/state", viewer, tmp_path / "viewer.log")
            yield url, session
    finally:
        fleet.stop(viewer, shard)


def _labels_v2() -> np.ndarray:
    labels = lane_tile()
    labels[:, NEW_LINE_COLS[0] : NEW_LINE_COLS[1]] = Cls.LANE_LINE
    return labels


def _ingest(session, labels, traversal: str, t_ns: int) -> None:
    fleet.ingest(session, IngestBatch(patches_from_labels(labels, tile=(0, 0),
                                                          traversal=traversal, t_ns=t_ns)))


class _PosePublisher(threading.Thread):
    """A localizer's pose stream, 5 Hz, until stopped."""

    def __init__(self, session):
        super().__init__(daemon=True)
        self.pub = session.declare_publisher(keys.pose("car-7"))
        self.halt = threading.Event()

    def run(self):
        while not self.halt.wait(0.2):
            self.pub.put(codec.encode(Pose("car-7", time.time_ns(), *POSE_XY, 0.6,
                                           np.eye(3) * 0.01, True)))

    def stop(self):
        self.halt.set()
        self.join(2.0)
        self.pub.undeclare()


def _wait(driver, script: str, timeout_s: float = 20.0, what: str = ""):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"page: {what or script} not true within {timeout_s:.0f} s")


def _screenshot(driver, name: str) -> np.ndarray:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    driver.save_screenshot(str(path))
    print(f"viewer screenshot: {path}")  # noqa: T201 (the test log names the artifact)
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def _screen(driver):
    """(canvas left, top, width, height) in screenshot pixels."""
    r = driver.execute_script("const r = document.getElementById('map').getBoundingClientRect();"
                              "return [r.left, r.top, r.width, r.height, "
                              "document.getElementById('panel').getBoundingClientRect().left];")
    return r


def _cells_on_screen(screen):
    """Cells (row, col) of tile (0, 0) whose centres show left of the panel, away from the
    tile's outline and the pose marker, and the screen pixel (py, px) of each centre."""
    left, top, w, h, panel_left = screen
    r, c = (g.ravel() for g in np.mgrid[2:510, 2:510])
    x, y = (c + 0.5) * 0.1, (r + 0.5) * 0.1
    px = np.floor(left + w / 2 + (x - CENTRE[0]) * SCALE).astype(int)
    py = np.floor(top + h / 2 - (y - CENTRE[1]) * SCALE).astype(int)
    pose = np.hypot(x - POSE_XY[0], y - POSE_XY[1]) < 2.5
    keep = (px >= 0) & (py >= 0) & (px < panel_left - 2) & (py < top + h) & ~pose
    return r[keep], c[keep], py[keep], px[keep]


def _classes_shown(image: np.ndarray, py, px) -> np.ndarray:
    """The palette class nearest to each sampled pixel's colour."""
    rgb = image[py, px].astype(int)
    d = np.abs(rgb[:, None, :] - COLORS_RGB[None].astype(int)).sum(axis=2)
    return np.argmin(d, axis=1)


def _agreement(image, screen, labels) -> dict:
    """Per class: how many of its cells are on screen, the share of them drawn in its colour
    (recall) and the share of the pixels in its colour that are its cells (precision)."""
    r, c, py, px = _cells_on_screen(screen)
    truth, shown = labels[r, c], _classes_shown(image, py, px)
    out = {}
    for cls in (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK):
        t, s = truth == cls, shown == cls
        out[cls.name.lower()] = {"cells": int(t.sum()),
                                 "recall": float((t & s).sum() / max(t.sum(), 1)),
                                 "precision": float((t & s).sum() / max(s.sum(), 1))}
    return out


def _map_labels(session) -> tuple[int, np.ndarray]:
    tile = fleet_queries.get_tile(session, (0, 0), timeout_s=5.0)
    return tile.version, decode_tile(tile.data)


def _assert_drawn(agreement: dict, classes=("lane_line", "stop_line", "crosswalk")):
    for name in classes:
        a = agreement[name]
        assert a["cells"] > 50, (name, a)
        assert a["recall"] >= 0.98 and a["precision"] >= 0.98, (name, a)


def test_page_shows_the_map_follows_updates_and_poses(live_viewer):
    url, session = live_viewer
    _ingest(session, lane_tile(), "t1", 10**12)
    poses = _PosePublisher(session)
    poses.start()
    driver = _chrome()
    try:
        driver.get(f"{url}?x={CENTRE[0]}&y={CENTRE[1]}&scale={SCALE}&poll=300")
        _wait(driver, "return window.roadmapViewer.shown()['0,0'] >= 1", what="tile 0,0 drawn")
        _wait(driver, "return window.roadmapViewer.poses().includes('car-7')", what="the pose")
        time.sleep(0.5)  # a poll after the pose arrived has redrawn the canvas
        version_1, labels_1 = _map_labels(session)
        screen = _screen(driver)
        first = _screenshot(driver, "01-map.png")
        _assert_drawn(_agreement(first, screen, labels_1))
        # the pose marker (a green triangle) sits at the pose
        left, top, w, h, _ = screen
        px = int(left + w / 2 + (POSE_XY[0] - CENTRE[0]) * SCALE)
        py = int(top + h / 2 - (POSE_XY[1] - CENTRE[1]) * SCALE)
        assert np.abs(first[py, px].astype(int) - POSE_RGB).sum() < 30, first[py, px]

        # a new patch (two more traversals with a second line) changes the tile: the page follows
        new_line = _labels_v2()
        _ingest(session, new_line, "t2", 2 * 10**12)
        _ingest(session, new_line, "t3", 3 * 10**12)
        deadline = time.monotonic() + 20.0
        while _map_labels(session)[0] == version_1 and time.monotonic() < deadline:
            time.sleep(0.2)
        version_2, labels_2 = _map_labels(session)
        assert version_2 > version_1
        assert (labels_2[:, NEW_LINE_COLS[0]] == Cls.LANE_LINE).mean() > 0.95  # the map moved
        _wait(driver, f"return window.roadmapViewer.shown()['0,0'] >= {version_2}",
              what=f"tile 0,0 at version {version_2}")
        time.sleep(0.3)
        second = _screenshot(driver, "02-after-new-patch.png")
        agreement = _agreement(second, screen, labels_2)
        _assert_drawn(agreement)
        r, c, py, px = _cells_on_screen(screen)
        on_new = (labels_2[r, c] == Cls.LANE_LINE) & (c >= NEW_LINE_COLS[0]) & (
            c < NEW_LINE_COLS[1])
        assert on_new.sum() > 100
        assert (_classes_shown(second, py, px)[on_new] == Cls.LANE_LINE).mean() >= 0.98
        assert (_classes_shown(first, py, px)[on_new] == Cls.LANE_LINE).mean() < 0.05

        # a click on the tile shows its version and its shard's stats
        from selenium.webdriver.common.action_chains import ActionChains

        canvas = driver.find_element("id", "map")
        dx = (25.0 - CENTRE[0]) * SCALE  # offsets from the canvas centre, to (25, 25) m
        dy = -(25.0 - CENTRE[1]) * SCALE
        ActionChains(driver).move_to_element_with_offset(canvas, int(dx), int(dy)).click().perform()
        _wait(driver, f"return document.getElementById('info').dataset.version == '{version_2}'",
              what="the tile info panel")
        info = driver.find_element("id", "info").text
        assert "s0" in info and "patches_applied" in info and "digest" in info, info
        _screenshot(driver, "03-tile-info.png")

        # zoom (the + button) and pan (a drag of 100 px to the right)
        scale_0 = driver.execute_script("return window.roadmapViewer.view.scale")
        driver.find_element("id", "zoom-in").click()
        scale_1 = driver.execute_script("return window.roadmapViewer.view.scale")
        assert scale_1 == pytest.approx(1.5 * scale_0)
        x_0 = driver.execute_script("return window.roadmapViewer.view.x")
        (ActionChains(driver).move_to_element_with_offset(canvas, -200, 0).click_and_hold()
         .move_by_offset(50, 0).move_by_offset(50, 0).release().perform())
        x_1 = driver.execute_script("return window.roadmapViewer.view.x")
        assert x_1 == pytest.approx(x_0 - 100 / scale_1, abs=0.05)
        _screenshot(driver, "04-zoomed-panned.png")
    finally:
        driver.quit()
        poses.stop()
