"""The suites' drives: (world, seed) pairs, each one `roadmap demo` run.

`default` covers the Karlsruhe Lanelet2 map, every Argoverse 2 log in the shared data and
procedural towns, each over a range of seeds that no default was tuned on; `quick` is a small
subset for a first look. Worlds of the shared data are left out, with a warning, when absent."""

import logging
from dataclasses import dataclass
from pathlib import Path

from services.sim.worlds import KARLSRUHE, shared_data_dir

logger = logging.getLogger(__name__)

# seeds of the suites: away from 0-36 and 101-108, which the demos and the localizer's settings
# were run on and tuned against (services/eval/replay.py); 5 seeds x (Karlsruhe, 3 Argoverse 2
# logs, town) = 25 drives, which fit the suite's 40 minutes on 2 cores
DEFAULT_SEEDS = range(201, 206)
QUICK_SEEDS = range(201, 203)
PRODUCTION_KM = 1.0  # the production drive's length where the world's route allows


@dataclass(frozen=True)
class Drive:
    world: str  # a load_world spec: town | town:<km> | lanelet2:PATH | av2:PATH
    seed: int

    @property
    def name(self) -> str:
        """A folder name: the world's short name and the seed."""
        kind, _, arg = self.world.partition(":")
        short = Path(arg).stem[:12] if arg and kind != "town" else (arg or "")
        return f"{kind}{'-' + short if short else ''}-s{self.seed}"


def shared_worlds() -> list[str]:
    """The Karlsruhe map and every Argoverse 2 log present in the shared data."""
    shared = shared_data_dir()
    worlds = []
    if (shared / KARLSRUHE).is_file():
        worlds.append(f"lanelet2:{shared / KARLSRUHE}")
    worlds += [f"av2:{p}" for p in sorted((shared / "av2").glob("*-*-*-*-*")) if p.is_dir()]
    if not worlds:
        logger.warning("no shared data at %s: the suite runs procedural towns only", shared)
    return worlds


def suite_drives(name: str) -> list[Drive]:
    """The drives of suite `name` (default | quick)."""
    if name == "quick":
        worlds = shared_worlds()[:1] + ["town"]
        return [Drive(w, s) for w in worlds for s in QUICK_SEEDS]
    if name == "default":
        worlds = shared_worlds() + ["town"]
        return [Drive(w, s) for w in worlds for s in DEFAULT_SEEDS]
    raise ValueError(f"unknown suite {name!r} (default | quick)")


def parse_seeds(text: str) -> list[int]:
    """'101-108' or '1,3,5' (or a mix: '1-3,7') -> sorted seeds."""
    seeds: set[int] = set()
    for part in text.split(","):
        a, _, b = part.strip().partition("-")
        if not a.strip().isdigit() or (b and not b.strip().isdigit()):
            raise ValueError(f"seeds: expected e.g. 101-108 or 1,3,5, got {text!r}")
        seeds.update(range(int(a), int(b or a) + 1))
    if not seeds:
        raise ValueError(f"seeds: none in {text!r}")
    return sorted(seeds)
