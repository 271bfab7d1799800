"""World sources by spec: "town" / "town:<km>" (procedural), "lanelet2:PATH" (Lanelet2 OSM),
"av2:PATH" (Argoverse 2 log); None = the Karlsruhe Lanelet2 map when the shared data exists,
else a 2 km town. Also `repaint`: the same world with one lane line moved sideways."""

import copy
import logging
import os
from pathlib import Path

import numpy as np

from common.classes import Cls
from common.errors import WorldError
from common.world import Marking, World
from services.sim import paint

logger = logging.getLogger(__name__)

KARLSRUHE = Path("lanelet2-karlsruhe") / "mapping_example.osm"


def shared_data_dir() -> Path:
    """$ROADMAP_SHARED_DATA, else ../shared/data beside the checkout the code runs from, else
    (an installed package) ../shared/data beside the working directory."""
    env = os.environ.get("ROADMAP_SHARED_DATA")
    if env:
        return Path(env)
    beside_checkout = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    if beside_checkout.is_dir():
        return beside_checkout
    return Path.cwd().resolve().parent / "shared" / "data"


def default_spec() -> str:
    path = shared_data_dir() / KARLSRUHE
    return f"lanelet2:{path}" if path.is_file() else "town"


def load_world(spec: str | None = None, seed: int = 0) -> World:
    """Build a World from its spec (see the module docstring)."""
    spec = spec or default_spec()
    kind, _, arg = spec.partition(":")
    if kind == "town":
        from services.sim.town import build_town

        try:
            km = float(arg) if arg else 2.0
        except ValueError as exc:
            raise WorldError(f"town size must be km, got {arg!r}") from exc
        return build_town(km, seed)
    if kind == "lanelet2":
        from services.sim.lanelet2 import load_lanelet2

        return load_lanelet2(_existing(arg or str(shared_data_dir() / KARLSRUHE)), seed)
    if kind == "av2":
        from services.sim.av2 import load_av2

        return load_av2(_existing(arg), seed)
    raise WorldError(f"unknown world {spec!r} (town | town:<km> | lanelet2:PATH | av2:PATH)")


def _existing(path: str) -> Path:
    p = Path(path).expanduser()
    if not p.exists():
        raise WorldError(f"world source not found: {p}")
    return p


def repaint(world: World, seed: int = 0, shift_m: float = 1.0) -> World:
    """A copy of the world with one lane line on a frequently driven road moved shift_m sideways.

    The chosen line (all its dashes) is the one nearest to a point 120-250 m into the first
    route, which every vehicle drives first (so short drives see it); it moves along the route's
    normal there."""
    rng = np.random.default_rng(seed)
    route = world.routes[0]
    s = paint.arc_length(route)
    at = min(rng.uniform(120.0, 250.0), 0.5 * s[-1])
    k = int(np.searchsorted(s, at))
    p = route[min(k, len(route) - 1)]
    d = route[min(k + 1, len(route) - 1)] - route[max(k - 1, 0)]
    normal = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9)
    lines = [i for i, m in enumerate(world.markings) if m.cls == Cls.LANE_LINE]
    if not lines:
        raise WorldError(f"{world.name}: no lane line to repaint")
    dist = [np.linalg.norm(world.markings[i].polygon_xy_m.mean(axis=0) - p) for i in lines]
    target = world.markings[lines[int(np.argmin(dist))]]
    group = [i for i in lines if _same_line(world.markings[i], target, p, 40.0)]
    out = copy.copy(world)
    out.markings = list(world.markings)
    for i in group:
        m = world.markings[i]
        out.markings[i] = Marking(m.cls, m.polygon_xy_m + shift_m * normal, m.kind)
    out.name = f"{world.name}-repaint{seed}"
    logger.info("repaint %s: moved %d lane-line polygons %.1f m", world.name, len(group), shift_m)
    return out


def _same_line(m: Marking, target: Marking, p: np.ndarray, radius_m: float) -> bool:
    """Polygons of the same painted line near p (same kind, centre within 0.3 m of its axis)."""
    c = m.polygon_xy_m.mean(axis=0)
    if m.kind != target.kind or np.linalg.norm(c - p) > radius_m:
        return False
    pts = target.polygon_xy_m
    axis = pts[len(pts) // 2 - 1] - pts[0]
    if np.linalg.norm(axis) < 1e-6:
        return m is target
    axis /= np.linalg.norm(axis)
    off = c - target.polygon_xy_m.mean(axis=0)
    return abs(off[0] * axis[1] - off[1] * axis[0]) < 0.3
