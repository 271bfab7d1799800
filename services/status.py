"""`roadmap status [--connect EP | --from DIR] [--json]`: the fleet at a glance.

Live: every stats queryable (`roadmap/stats/<role>/<id>`) sampled twice, `--interval` apart, for
the rates (patches/s applied per shard), and the liveliness tokens (`roadmap/alive/<role>/<id>`)
for who is alive (shards, vehicles, localizers, viewers). From disk: the shard stores of a demo's
output folder (patches and tiles each holds), no rates and nobody alive."""

import json
import logging
import sys
import time

from common.grid import region_of_tile
from services import fleet

logger = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 5.0  # no router within this: a one-line error, not a wait

ROLES = ("merger", "vehicle", "localizer", "viewer")


def fleet_status(session, *, interval_s: float = 1.0, timeout_s: float = 2.0) -> dict:
    """The status of a running fleet (see format_status for what it holds)."""
    first, t_first = fleet.all_stats(session, timeout_s), time.monotonic()
    time.sleep(max(0.0, interval_s))
    second, t_second = fleet.all_stats(session, timeout_s), time.monotonic()
    alive = fleet.alive(session, timeout_s)
    dt = max(t_second - t_first, 1e-9)
    shards = []
    for (role, ident), counters in sorted(second.items()):
        if role != "merger":
            continue
        before = first.get((role, ident), {})
        rate = (float(counters.get("patches_applied", 0))
                - float(before.get("patches_applied", 0))) / dt if before else None
        shards.append(_shard_row(ident, counters, rate, ident in alive.get("merger", [])))
    others = {f"{role}/{ident}": _visible(c) for (role, ident), c in sorted(second.items())
              if role != "merger"}
    return _summary("fleet", shards, alive, others, interval_s=round(dt, 3))


def folder_status(path) -> dict:
    """The status a demo's output folder (its shard stores) records."""
    from services.export.sources import read_folder

    stored = read_folder(path)
    tiles_of: dict[str, list] = {}
    for tile, shard in stored.owners.items():
        tiles_of.setdefault(shard, []).append(tile)
    shards = [{"id": row["shard"], "alive": None, "tiles": row["tiles"],
               "regions": len({region_of_tile(t) for t in tiles_of.get(row["shard"], [])}),
               "patches_applied": row["patches"], "patches_per_s": None, "duplicates": None,
               "errors": None, "digest": None, "store": row["path"]} for row in stored.stores]
    if not stored.stores:  # a tiles.npz: tiles only
        shards = [{"id": "?", "alive": None, "tiles": len(stored.tiles),
                   "regions": len({region_of_tile(tuple(t.tile)) for t in stored.tiles}),
                   "patches_applied": None, "patches_per_s": None, "duplicates": None,
                   "errors": None, "digest": None}]
    return _summary(f"folder {path}", shards, {}, {})


def _shard_row(ident: str, counters: dict, rate: float | None, alive: bool) -> dict:
    tiles = fleet.tile_list(counters)
    return {"id": ident, "alive": alive, "tiles": int(counters.get("tiles", len(tiles))),
            "regions": len({region_of_tile(t) for t in tiles}),
            "patches_applied": int(counters.get("patches_applied", 0)),
            "patches_per_s": None if rate is None else round(rate, 2),
            "duplicates": int(counters.get("duplicates", 0)),
            "errors": int(counters.get("errors", 0)),
            "digest": counters.get("digest")}


def _visible(counters: dict) -> dict:
    return {k: v for k, v in counters.items() if k != "tile_list"}


def _summary(source: str, shards: list[dict], alive: dict, others: dict, **extra) -> dict:
    def total(key):
        values = [s[key] for s in shards if s.get(key) is not None]
        return round(sum(values), 2) if values else None

    answering = {s["id"] for s in shards}
    return {
        "source": source, **extra,
        "shards": shards,
        "totals": {"shards": len(shards), "tiles": total("tiles"), "regions": total("regions"),
                   "patches_applied": total("patches_applied"),
                   "patches_per_s": total("patches_per_s")},
        "alive": {role: alive.get(role, []) for role in sorted(set(ROLES) | set(alive))},
        "counts": {"vehicles_alive": len(alive.get("vehicle", [])),
                   "localizers_alive": len(alive.get("localizer", [])),
                   "shards_alive": len(alive.get("merger", [])),
                   # a token without stats (a shard still recovering, or its queryable gone)
                   "shards_silent": sorted(set(alive.get("merger", [])) - answering)},
        "other_stats": others,
    }


def format_status(s: dict) -> str:
    """A few lines for a terminal."""
    t, c = s["totals"], s["counts"]
    rate = "" if t["patches_per_s"] is None else f", {t['patches_per_s']:.1f} patches/s"
    lines = [f"roadmap status ({s['source']}): {t['shards']} shards, {t['tiles'] or 0} tiles in "
             f"{t['regions'] or 0} regions, {t['patches_applied'] or 0} patches applied{rate}",
             f"  {'shard':8s}{'alive':>6s}{'tiles':>7s}{'regions':>8s}{'patches':>9s}"
             f"{'per s':>8s}{'dups':>6s}{'errors':>7s}  digest"]
    for r in s["shards"]:
        alive = "-" if r["alive"] is None else ("yes" if r["alive"] else "NO")
        lines.append(f"  {r['id']:8s}{alive:>6s}{r['tiles']:>7d}{r['regions']:>8d}"
                     f"{_n(r['patches_applied']):>9s}{_n(r['patches_per_s'], '{:.1f}'):>8s}"
                     f"{_n(r['duplicates']):>6s}{_n(r['errors']):>7s}  "
                     f"{(r['digest'] or '-')[:12]}")
    if c["shards_silent"]:
        lines.append(f"  alive but not answering stats: {', '.join(c['shards_silent'])}")
    for role in ("vehicle", "localizer", "viewer"):
        ids = s["alive"].get(role, [])
        lines.append(f"{role + 's alive':18s}{len(ids):>3d}  {' '.join(ids)}".rstrip())
    return "\n".join(lines) + "\n"


def _n(v, fmt: str = "{}") -> str:
    return "-" if v is None else fmt.format(v)


def status_command(args, cfg) -> int:
    if args.from_dir:
        status = folder_status(args.from_dir)
    else:
        from common.bus import open_session

        with open_session(cfg.bus, connect_timeout_s=CONNECT_TIMEOUT_S) as session:
            time.sleep(0.2)  # let the router's routing table reach this new session
            status = fleet_status(session, interval_s=args.interval,
                                  timeout_s=min(cfg.bus.query_timeout_s, 2.0))
    sys.stdout.write(json.dumps(status, indent=1) + "\n" if args.json else format_status(status))
    return 0
