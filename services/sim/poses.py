"""Poses and traffic for frames rendered away from a drive (the segmentation model's held-out
and training frames): a random pose on a world's routes, facing rare markings on request, and
random cars around it."""

import math

import numpy as np

from common.classes import Cls


def random_pose(world, rng, rare_prob: float = 0.5, turn_prob: float = 0.0):
    """(x, y, yaw) on a route, jittered sideways and in heading; with `rare_prob` a pose that
    looks at a stop line, crosswalk or ground sign 4-20 m ahead (those classes are rare); with
    `turn_prob` (training) the heading turned 15-90 deg off the route, as when turning across a
    junction: lane lines then cross the view like stop lines, and only their width tells."""
    pose = _route_pose(world, rng, rare_prob)
    if turn_prob and rng.random() < turn_prob:
        turn = rng.choice([-1.0, 1.0]) * rng.uniform(math.radians(15), math.radians(90))
        pose = (pose[0], pose[1], pose[2] + float(turn))
    return pose


def _route_pose(world, rng, rare_prob):
    rare = [m for m in world.markings if m.cls in (Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)]
    if rare and rng.random() < rare_prob:
        target = rare[int(rng.integers(len(rare)))].polygon_xy_m.mean(axis=0)
        for route in world.routes:
            d = target - route
            dist = np.hypot(d[:, 0], d[:, 1])
            heading = np.gradient(route, axis=0)
            facing = (d * heading).sum(1) > 0.8 * dist * np.hypot(heading[:, 0], heading[:, 1])
            ok = np.flatnonzero((dist > 4.0) & (dist < 20.0) & facing)
            if len(ok):
                return _pose_on(route, int(rng.choice(ok)), rng)
    route = world.routes[int(rng.integers(len(world.routes)))]
    return _pose_on(route, int(rng.integers(0, len(route) - 2)), rng)


def _pose_on(route, i, rng):
    i = min(i, len(route) - 2)
    d = route[i + 1] - route[i]
    yaw = math.atan2(d[1], d[0]) + rng.normal(0, 0.05)
    normal = np.array([-math.sin(yaw), math.cos(yaw)])
    xy = route[i] + normal * rng.normal(0, 0.4)
    return float(xy[0]), float(xy[1]), yaw


def random_cars(pose, rng) -> list:
    """A lead car (sometimes) and parked cars at the right (sometimes), as the simulator does."""
    from services.sim.render import Vehicle

    cars = []
    colour = lambda: tuple(rng.uniform(20, 220, 3))  # noqa: E731
    if rng.random() < 0.35:
        cars.append(Vehicle(rng.uniform(8, 30), rng.normal(0, 0.4), rng.normal(0, 0.05),
                            rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7),
                            colour(), relative=True))
    for _ in range(int(rng.poisson(0.6))):
        cars.append(Vehicle(rng.uniform(5, 40), -rng.uniform(2.9, 3.8), rng.normal(0, 0.05),
                            rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7),
                            colour(), relative=True))
    return cars
