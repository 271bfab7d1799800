"""RegionTable.owner (services/merger/worker.py): merger.region_owners pins a region to a live
worker; otherwise, and once that worker is gone, rendezvous hashing over the live ones."""

from common.grid import owner_among
from services.merger.worker import RegionTable


def _table(ident, pins):
    return RegionTable(ident=ident, write_db=None, control_db=None, lease_s=4.0,
                       merger_cfg=None, region_owners=pins)


def test_a_pinned_region_goes_to_its_worker_while_it_lives():
    region = next(r for r in ((x, 0) for x in range(50)) if owner_among(r, ["s0", "s1"]) == "s1")
    table = _table("s0", {f"{region[0]},{region[1]}": "s0"})
    assert table.owner(region, {"s0", "s1"}) == "s0"
    assert table.owner(region, {"s1"}) == "s1"  # the pinned worker is gone: rendezvous
    assert table.owner((region[0], 99), {"s0", "s1"}) == owner_among((region[0], 99),
                                                                     ["s0", "s1"])
