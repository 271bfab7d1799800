"""The renderer: markings land in the image exactly where the camera model projects them;
label images invert through the IPM table; RGB frames are seeded, reproducible and fast enough
to be worth benchmarking (timing lives in services/bench/render.py)."""

import cv2
import numpy as np
import pytest

from common.camera import build_ipm_lookup, camera_from_config
from common.classes import Cls
from common.config import CameraConfig
from common.world import Marking, World
from services.sim.render import FrameRenderer, LabelRenderer, Vehicle, motion_kernel

POSE = np.array([100.0, 50.0, 0.3])


def _square(cx, cy, half, cls=Cls.GROUND_SIGN):
    return Marking(
        cls,
        np.array(
            [
                [cx - half, cy - half],
                [cx + half, cy - half],
                [cx + half, cy + half],
                [cx - half, cy + half],
            ]
        ),
    )


def _world_with_square(x_v, y_v, half=0.4):
    """A road and one square marking centred at (x_v, y_v), axis-aligned in the vehicle frame."""
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    sq = _square(x_v, y_v, half).polygon_xy_m
    world_sq = sq @ np.array([[c, s], [-s, c]]) + POSE[:2]
    road = _square(POSE[0], POSE[1], 60.0, Cls.ROAD)
    return World("square", [road, Marking(Cls.GROUND_SIGN, world_sq)]), world_sq.mean(axis=0)


@pytest.fixture(scope="module")
def camera():
    return camera_from_config(CameraConfig())


@pytest.mark.parametrize("x_v, y_v", [(8.0, 0.0), (12.0, 2.5), (6.0, -1.5)])
def test_marking_lands_where_the_camera_projects_it(camera, x_v, y_v):
    world, _ = _world_with_square(x_v, y_v)
    lab, _, _ = LabelRenderer(world, camera).labels(POSE, camera.T_vehicle_camera)
    uv, front = camera.project_vehicle_points(np.array([[x_v, y_v, 0.0]]))
    assert front[0]
    u, v = np.floor(uv[0]).astype(int)
    assert lab[v, u] == Cls.GROUND_SIGN
    # the blob lies between the projections of the square shrunk and grown by one 0.1 m cell
    vv, uu = np.nonzero(lab == Cls.GROUND_SIGN)
    for grow, inside in ((0.11, True), (-0.11, False)):
        h = 0.4 + grow
        corners = np.array([[x_v + dx, y_v + dy, 0.0] for dx in (-h, h) for dy in (-h, h)])
        cuv, _ = camera.project_vehicle_points(corners)
        if inside:  # every labelled pixel is inside the grown square
            assert cuv[:, 0].min() - 1 <= uu.min() and uu.max() <= cuv[:, 0].max() + 1
            assert cuv[:, 1].min() - 1 <= vv.min() and vv.max() <= cuv[:, 1].max() + 1
        else:  # every pixel of the shrunk square is labelled
            u0, u1 = np.ceil(cuv[:, 0].min()), np.floor(cuv[:, 0].max())
            v0, v1 = np.ceil(cuv[:, 1].min()), np.floor(cuv[:, 1].max())
            assert (lab[int(v0) : int(v1), int(u0) : int(u1)] == Cls.GROUND_SIGN).mean() > 0.95


def test_labels_invert_through_the_ipm_table(camera):
    world, _ = _world_with_square(9.0, 1.0, half=0.5)
    lab, _, _ = LabelRenderer(world, camera).labels(POSE, camera.T_vehicle_camera)
    ipm = build_ipm_lookup(camera, x_min_m=3.0, length_m=12.0, width_m=8.0)
    xy, cls = ipm.lookup(lab)
    sign = xy[cls == Cls.GROUND_SIGN]
    assert len(sign) > 50
    assert np.all(np.abs(sign - [9.0, 1.0]) <= 0.5 + 0.15)  # + one cell diagonal
    # pixel means lean to the near side (perspective); the extent is centred on the square
    mid = (sign.min(axis=0) + sign.max(axis=0)) / 2.0
    assert np.allclose(mid, [9.0, 1.0], atol=0.07)


def test_no_labels_above_the_horizon(camera):
    world, _ = _world_with_square(10.0, 0.0)
    lab, geo, _ = LabelRenderer(world, camera).labels(POSE, camera.T_vehicle_camera)
    assert (lab[~geo.ground] == 0).all()
    assert (lab[: int(camera.K[1, 2]) - 40] == 0).all()


def test_rgb_is_seeded_and_reproducible(camera):
    world, _ = _world_with_square(10.0, 0.0)
    a = FrameRenderer(world, camera, seed=7).render(POSE, camera.T_vehicle_camera, 0.0)
    b = FrameRenderer(world, camera, seed=7).render(POSE, camera.T_vehicle_camera, 0.0)
    c = FrameRenderer(world, camera, seed=8).render(POSE, camera.T_vehicle_camera, 0.0)
    assert a[0].shape == (camera.height, camera.width, 3) and a[0].dtype == np.uint8
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_paint_is_brighter_than_asphalt(camera):
    world, _ = _world_with_square(8.0, 0.0, half=0.6)
    r = FrameRenderer(world, camera, seed=1)
    r.look.fade, r.look.wear_level, r.look.shadow_strength = 1.0, 0.0, 0.0
    rgb, lab = r.render(POSE, camera.T_vehicle_camera, 0.0)
    grey = rgb.astype(float).mean(axis=2)
    assert grey[lab == Cls.GROUND_SIGN].mean() > grey[lab == Cls.ROAD].mean() + 40


def test_other_vehicles_occlude_the_road_and_get_label_zero(camera):
    world, _ = _world_with_square(10.0, 0.0)
    r = FrameRenderer(world, camera, seed=2)
    lead = Vehicle(10.0, 0.0, 0.0, 4.4, 1.8, 1.5, (200, 30, 30), relative=True)
    _, free = r.render(POSE, camera.T_vehicle_camera, 0.0)
    rgb, lab = r.render(POSE, camera.T_vehicle_camera, 0.0, [lead])
    uv, _ = camera.project_vehicle_points(np.array([[8.6, 0.0, 0.5]]))  # its rear, low
    u, v = np.round(uv[0]).astype(int)
    assert free[v, u] != 0 and lab[v, u] == 0
    assert (lab == Cls.GROUND_SIGN).sum() < (free == Cls.GROUND_SIGN).sum()


def _vehicle_rect(x0, x1, y0, y1):
    """A ROAD rectangle given in the vehicle frame of POSE, in world coordinates."""
    c, s = np.cos(POSE[2]), np.sin(POSE[2])
    pts = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return Marking(Cls.ROAD, pts @ np.array([[c, s], [-s, c]]) + POSE[:2])


def test_raised_island_hides_the_road_behind_it_and_shows_a_curb_face(camera):
    """Two roads ahead with a 1 m raised island between them (x 10-11 m in the vehicle frame):
    with raised curbs the island's curb hides a band of the far road just behind it (label 0
    there), exactly the band the curb height predicts; without curbs nothing is hidden."""
    world = World("island", [_vehicle_rect(-5, 10, -8, 8), _vehicle_rect(11, 60, -8, 8)])
    r = FrameRenderer(world, camera, seed=3)
    r.look.curb, r.look.curb_h_m = False, 0.15
    flat = r.labels(POSE, camera.T_vehicle_camera)
    r.look.curb = True
    raised = r.labels(POSE, camera.T_vehicle_camera)
    hidden = (flat == Cls.ROAD) & (raised == 0)
    assert hidden.sum() > 50
    assert ((raised != 0) & (flat != raised)).sum() == 0  # only ever hides, never adds
    # ground distance of the hidden pixels: from 11 m out to where a 0.15 m curb at 11 m
    # stops hiding the ground, x_cam + (11 - x_cam) * H / (H - h)
    x_cam, height = camera.T_vehicle_camera[0, 3], camera.T_vehicle_camera[2, 3]
    far = x_cam + (11.0 - x_cam) * height / (height - 0.15)
    vv, uu = np.nonzero(hidden)
    v = vv[len(vv) // 2]  # a pixel row in the middle of the band
    top, bottom = camera.project_vehicle_points(np.array([[far, 0.0, 0.0], [11.0, 0.0, 0.0]]))[0]
    assert top[1] - 2 <= v <= bottom[1] + 2
    # the face of the island's near curb: darker than the curb top when in shade
    r.look.curb_face, r.look.shadow_strength, r.look.sidewalk_m = 0.4, 0.0, 0.0
    rgb, lab = r.render(POSE, camera.T_vehicle_camera, 0.0)
    (_, v_face), (_, v_top) = np.round(camera.project_vehicle_points(
        np.array([[10.02, 0.0, 0.07], [10.5, 0.0, 0.15]]))[0]).astype(int)
    grey = rgb.astype(float).mean(axis=2)
    u0 = camera.width // 2
    assert lab[v_face, u0] == 0 and lab[v_top, u0] == 0
    assert grey[v_face, u0 - 3:u0 + 4].mean() < 0.8 * grey[v_top, u0 - 3:u0 + 4].mean()


def test_frames_at_unrelated_poses_compute_their_box_of_the_window_with_the_same_bytes(camera):
    """A renderer for frames at unrelated poses (`jumps`: training frames) computes the
    surface masks (road, paint, curb, sidewalk) of only the box of the label window that a
    frame reads, not of the whole window as a drive's renderer does (a frame at a random pose
    reads about a quarter of it). Inside the box's margin the masks are the whole window's,
    and the frames are the same bytes: the margin covers the blur and the curb and sidewalk
    rings (a narrower margin fails this test)."""
    from services.sim.worlds import load_world
    from training.synth import random_pose

    world = load_world("town", seed=2)
    rng = np.random.default_rng(5)
    curbs = 0
    for i in range(4):
        pose = random_pose(world, rng, turn_prob=0.2)  # as training frames are posed
        boxed = FrameRenderer(world, camera, seed=i, jumps=True)
        whole = FrameRenderer(world, camera, seed=i)
        for r in (boxed, whole):
            r.look.curb, r.look.sidewalk_m, r.look.curb_w_m = True, 3.0, 0.2  # widest rings
        T = camera.T_vehicle_camera
        _, geo, (window, mx, my) = boxed.labeler.labels(pose, T)
        masks, x0, y0 = boxed._surface(window, mx, my, geo.ground, boxed._camera_cell(pose, T))
        h, w = masks.shape[:2]
        assert h * w < 0.6 * window.size  # a box, not the window
        m = boxed._surface_margin_cells()
        rows = slice(m if y0 else 0, h - m if y0 + h < window.shape[0] else h)
        cols = slice(m if x0 else 0, w - m if x0 + w < window.shape[1] else w)
        truth = whole._surface(window, mx, my, geo.ground, None)[0][y0:y0 + h, x0:x0 + w]
        assert np.array_equal(masks[rows, cols], truth[rows, cols])
        a = boxed.render(pose, T, 1.0, curb_label=6)
        b = whole.render(pose, T, 1.0, curb_label=6)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        curbs += int((a[1] == 6).sum())
    assert curbs > 1000  # curbs in view: the rings were read


def test_motion_blur_keeps_the_image_where_its_labels_are():
    image = np.zeros((21, 21), np.float32)
    image[10, 10] = 1.0
    rng = np.random.default_rng(0)
    for _ in range(40):  # every length and both directions the looks draw
        blurred = cv2.filter2D(image, -1, motion_kernel(rng))
        ys, xs = np.nonzero(blurred)
        w = blurred[ys, xs]
        assert blurred.sum() == pytest.approx(1.0)
        assert np.average(ys, weights=w) == pytest.approx(10.0)
        assert np.average(xs, weights=w) == pytest.approx(10.0)


def test_a_drives_next_label_window_carries_the_surface_masks_over_with_the_same_bytes(camera):
    """Along a drive the label window moves by whole tiles; the next window's surface masks
    (road, paint, curb, sidewalk) are the last window's where the two overlap and are computed
    only in the strips along its new edges: the same bytes as the whole window's masks, with
    the widest rings (a margin narrower than theirs fails this test)."""
    from services.sim.worlds import load_world

    world = load_world("town", seed=2)
    r = FrameRenderer(world, camera, seed=0)
    r.look.curb, r.look.sidewalk_m, r.look.curb_w_m = True, 3.0, 0.2  # widest rings
    route = world.routes[0]
    step = np.linalg.norm(np.diff(route, axis=0), axis=1).mean()
    moves, last = 0, None
    for x, y in route[:: max(1, int(10.0 / step))]:  # every 10 m: each tile of the route
        window, x0, y0 = r.labeler.tiles.window(x, y)
        if window is last:
            continue
        masks = r._surface(window, None, None, None, None, origin_m=(x0, y0))[0]
        if last is not None:
            assert np.array_equal(masks, r._surface_masks(window))
            moves += 1
        last = window
        if moves == 3:
            break
    assert moves == 3


def test_labels_alone_are_the_rendered_frames_labels_under_a_vibrating_camera(camera):
    """The label-only path (a drive without images) gives the labels of the RGB path; no
    pixel off the ground (above the horizon, pitched and rolled) gets a label, and rows that
    see no ground are sky only."""
    from services.sim.worlds import load_world

    world = load_world("town", seed=2)
    pose = np.array([*world.routes[0][5], 0.0])
    pose[2] = np.arctan2(*(world.routes[0][6] - world.routes[0][5])[::-1])
    rgb_r, lab_r = FrameRenderer(world, camera, seed=4), FrameRenderer(world, camera, seed=4)
    for d_pitch, d_roll in ((0.0, 0.0), (0.02, 0.05), (-0.03, -0.08)):
        T = camera.perturbed(d_pitch_rad=d_pitch, d_roll_rad=d_roll).T_vehicle_camera
        rgb, lab = rgb_r.render(pose, T, 0.0)
        assert np.array_equal(lab_r.labels(pose, T), lab)
        geo = rgb_r.labeler.geometry(pose, T)
        assert (lab[~geo.ground] == 0).all() and (lab > 0).sum() > 1000
        assert geo.ground[: geo.rows.start].sum() == 0 and geo.ground[geo.rows.stop :].sum() == 0
        assert rgb.shape == (camera.height, camera.width, 3) and rgb[0].mean() > 0
