"""Attacks on a real router over mutual TLS with the role ACL (`roadmap router` with
bus.tls_dir) and a real merger shard process behind it: who cannot connect, what each role's
certificate cannot do, that a forged tile never reaches a localizer, and hostile ingest through
the node (oversized, garbage, a flooding vehicle) answered with errors while others go on."""

import datetime
import os
import time

import pytest

from common import codec, keys
from common.bus import ZError, make_zenoh_config, open_session, wait_for_tcp
from common.config import BusConfig
from common.contours import CODEC, encode_tile
from common.messages import THROTTLED, IngestAck, IngestBatch, Stats, Tile
from common.security import write_certs
from services.localizer.map_cache import TileCache
from services.localizer.tiles import TileClient
from tests.conftest import spawn
from tests.merger.helpers import lane_tile, patches_from_labels

pytestmark = pytest.mark.integration

MAX_INGEST_BYTES = 200_000  # the shard under test refuses more, before decoding
RATE, BURST = 2.0, 6  # and admits each client this often


def _stop(proc) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except Exception:  # noqa: BLE001 - never leave it running
            proc.kill()
            proc.wait(5)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """certs (ours and another CA's), a secure router, merger shard s0 of 1; yields a dict."""
    from common.bus import free_tcp_port

    base = tmp_path_factory.mktemp("secure")
    certs, other = base / "certs", base / "other-ca"
    write_certs(certs)
    write_certs(other)
    port = free_tcp_port()
    endpoint = f"tls/127.0.0.1:{port}"
    env = dict(os.environ, ROADMAP_BUS__TLS_DIR=str(certs), ROADMAP_MERGER__DEBOUNCE_S="0.1",
               ROADMAP_MERGER__MAX_INGEST_BYTES=str(MAX_INGEST_BYTES),
               ROADMAP_MERGER__INGEST_RATE_PER_S=str(RATE),
               ROADMAP_MERGER__INGEST_BURST=str(BURST), ROADMAP_MERGER__THROTTLE_DELAY_S="0.05")
    router = spawn("router", "--listen", endpoint, env=env)
    merger = None
    try:
        assert wait_for_tcp("127.0.0.1", port, 15.0), router.stderr.read().decode()[-2000:]
        merger = spawn("merger", "--shard", 0, "--shards", 1, "--store", base / "s0.sqlite",
                       "--connect", endpoint, "--log-level", "WARNING", env=env)
        fleet = {"certs": certs, "other": other, "endpoint": endpoint, "merger": merger}
        with _session(fleet, "monitor") as mon:
            deadline = time.monotonic() + 30
            while not list(mon.liveliness().get(keys.alive("merger", "s0"), timeout=1.0)):
                assert merger.poll() is None, merger.stderr.read().decode()[-3000:]
                assert time.monotonic() < deadline, "merger did not come up"
                time.sleep(0.2)
        yield fleet
    finally:
        if merger is not None:
            _stop(merger)
        _stop(router)


def _bus(fleet, certs=None) -> BusConfig:
    return BusConfig(connect=[fleet["endpoint"]], tls_dir=str(certs or fleet["certs"]))


def _session(fleet, role, certs=None):
    return open_session(_bus(fleet, certs), role)


def _try_open(conf) -> bool:
    """Whether a client with this config gets a session (2 s to connect, then it gives up)."""
    import zenoh

    conf.insert_json5("connect/timeout_ms", "2000")
    conf.insert_json5("connect/exit_on_failure", "true")
    try:
        session = zenoh.open(conf)
    except ZError:
        return False
    session.close()
    return True


def _patches(traversal: str, vehicle: str = "veh-a", t_ns: int = 10**12):
    return patches_from_labels(lane_tile(), tile=(0, 0), traversal=traversal, t_ns=t_ns,
                               vehicle=vehicle, n_patches=2)


def _ingest(session, payload: bytes, client: str = "veh-a") -> IngestAck | None:
    for reply in session.get(keys.ingest(0), payload=payload, attachment=client.encode(),
                             timeout=3.0):
        if reply.ok is not None:
            return codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
    return None


def _stats(fleet) -> dict:
    with _session(fleet, "monitor") as mon:
        time.sleep(0.1)
        for reply in mon.get(keys.stats("merger", "s0"), timeout=3.0):
            if reply.ok is not None:
                return codec.decode(reply.ok.payload.to_bytes(), expect=Stats).counters
    raise AssertionError("no stats reply")


def _replies(session, selector, **kw) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(selector, timeout=2.0, **kw)
            if r.ok is not None]


# -- who gets in --------------------------------------------------------------------------------


def test_the_role_certificates_connect(fleet):
    assert _try_open(make_zenoh_config(_bus(fleet), "vehicle"))


def test_rotated_role_certificates_connect_to_the_running_router(fleet, tmp_path):
    import shutil

    shutil.copytree(fleet["certs"], tmp_path / "rotated")
    write_certs(tmp_path / "rotated", reuse_ca=True)  # new role certificates, the same CA
    assert (tmp_path / "rotated" / "vehicle.pem").read_bytes() != (
        fleet["certs"] / "vehicle.pem").read_bytes()
    assert _try_open(make_zenoh_config(_bus(fleet, tmp_path / "rotated"), "vehicle"))


def test_a_client_without_a_certificate_cannot_connect(fleet):
    conf = make_zenoh_config(_bus(fleet), "vehicle")
    conf.insert_json5("transport/link/tls/connect_certificate", "null")
    conf.insert_json5("transport/link/tls/connect_private_key", "null")
    assert not _try_open(conf)
    plain = make_zenoh_config(BusConfig(connect=[fleet["endpoint"].replace("tls/", "tcp/")]))
    assert not _try_open(plain)  # nor one without TLS


def test_a_certificate_from_another_ca_cannot_connect(fleet):
    conf = make_zenoh_config(_bus(fleet, fleet["other"]), "vehicle")
    # it even trusts our CA, so it is the router that refuses its certificate
    conf.insert_json5("transport/link/tls/root_ca_certificate",
                      f'"{fleet["certs"] / "ca.pem"}"')
    assert not _try_open(conf)
    assert not _try_open(make_zenoh_config(_bus(fleet, fleet["other"]), "vehicle"))


def test_a_certificate_of_no_role_can_do_nothing(fleet, tmp_path):
    _stranger_certs(fleet["certs"], tmp_path)  # our CA, common name "intruder"
    with open_session(_bus(fleet, tmp_path), "vehicle") as s:
        time.sleep(0.2)
        assert _replies(s, keys.ingest(0), payload=codec.encode(IngestBatch(_patches("x")))) == []
        assert _replies(s, keys.stats("merger", "s0")) == []
        assert list(s.liveliness().get(keys.alive_all("merger"), timeout=1.0)) == []


def _stranger_certs(ca_dir, out):
    """A copy of ca.pem and a certificate with common name 'intruder' as vehicle.pem/.key."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    from common import security

    ca_cert = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
    ca_key = serialization.load_pem_private_key((ca_dir / "ca.key").read_bytes(), None)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = security._role_certificate("intruder", key, ca_cert, ca_key, ("intruder",),
                                      datetime.datetime.now(datetime.UTC), 1)
    (out / "ca.pem").write_bytes((ca_dir / "ca.pem").read_bytes())
    (out / "vehicle.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    security._write_key(out / "vehicle.key", key)


# -- what each role cannot do -------------------------------------------------------------------


def test_a_vehicle_cannot_forge_tiles_nor_read_them(fleet):
    genuine_tile = Tile((0, 0), 999, CODEC, encode_tile(lane_tile(offset_cells=40)))
    forged = codec.encode(genuine_tile)
    with _session(fleet, "vehicle") as veh, _session(fleet, "localizer") as loc:
        ack = _ingest(veh, codec.encode(IngestBatch(_patches("forge-0"))))
        assert ack is not None and ack.error is None  # it can do its own work
        cache = TileCache(capacity=4)
        client = TileClient(loc, cache, timeout_s=3.0)
        try:
            def answer_forged(q):
                with q:
                    q.reply(q.key_expr, forged)

            fake = veh.declare_queryable("roadmap/tile/**", answer_forged, complete=True)
            time.sleep(0.5)
            veh.put(keys.tile_update(0, 0), forged)  # a forged update, published
            deadline = time.monotonic() + 10
            while (0, 0) not in cache:  # the merger's real tile, after its debounce
                assert time.monotonic() < deadline, "the localizer never got the tile"
                client.ensure([(0, 0)])
                time.sleep(0.2)
            time.sleep(0.5)
            client.poll_updates()
            assert cache.version((0, 0)) != 999 and client.rejected == 0
            all_replies = _replies(loc, keys.tile(0, 0), target=_query_all(),
                                   consolidation=_no_consolidation())
            assert forged not in all_replies and len(all_replies) == 1  # only the merger's
            fake.undeclare()
            time.sleep(0.2)
            assert _replies(veh, keys.tile(0, 0)) == []  # nor may it read the map
            assert _replies(veh, keys.stats("merger", "s0")) == []
        finally:
            client.close()


def _query_all():
    from common.bus import QueryTarget

    return QueryTarget.ALL


def _no_consolidation():
    from common.bus import ConsolidationMode

    return ConsolidationMode.NONE


def test_a_localizer_cannot_ingest(fleet):
    before = _stats(fleet)["patches_applied"]
    with _session(fleet, "localizer") as loc:
        time.sleep(0.2)
        payload = codec.encode(IngestBatch(_patches("from-localizer")))
        assert _replies(loc, keys.ingest(0), payload=payload) == []
        assert _replies(loc, keys.stats("merger", "s0")) == []
    assert _stats(fleet)["patches_applied"] == before


def test_a_monitor_reads_stats_and_liveliness_only(fleet):
    with _session(fleet, "monitor") as mon:
        time.sleep(0.2)
        assert len(_replies(mon, keys.stats("merger", "s0"))) == 1
        alive = [str(r.ok.key_expr) for r in mon.liveliness().get("roadmap/alive/**", timeout=1.0)
                 if r.ok is not None]
        assert keys.alive("merger", "s0") in alive
        assert _replies(mon, keys.tile(0, 0)) == []
        payload = codec.encode(IngestBatch(_patches("from-monitor")))
        assert _replies(mon, keys.ingest(0), payload=payload) == []


def test_a_vehicle_cannot_pose_as_a_merger(fleet):
    with _session(fleet, "vehicle") as veh, _session(fleet, "monitor") as mon:
        token = veh.liveliness().declare_token(keys.alive("merger", "s7"))
        own = veh.liveliness().declare_token(keys.alive("vehicle", "veh-a"))
        time.sleep(0.3)
        alive = {str(r.ok.key_expr) for r in mon.liveliness().get("roadmap/alive/**", timeout=1.0)
                 if r.ok is not None}
        assert keys.alive("vehicle", "veh-a") in alive
        assert keys.alive("merger", "s7") not in alive
        token.undeclare()
        own.undeclare()


# -- hostile ingest through the node ----------------------------------------------------------


def test_oversized_and_garbage_ingest_get_error_acks(fleet):
    before = _stats(fleet)
    with _session(fleet, "vehicle") as veh:
        time.sleep(0.2)
        big = _ingest(veh, b"\x00" * (MAX_INGEST_BYTES + 1), client="veh-big")
        assert big is not None and "max_ingest_bytes" in big.error
        bad = _ingest(veh, b"\xc1 not msgpack", client="veh-bad")
        assert bad is not None and "IngestBatch" in bad.error
    after = _stats(fleet)
    assert after["refused_oversize"] == before["refused_oversize"] + 1
    assert after["errors"] == before["errors"] + 1
    assert after["patches_applied"] == before["patches_applied"]


def test_a_flooding_vehicle_is_throttled_and_the_others_are_not(fleet):
    with _session(fleet, "vehicle") as flooder, _session(fleet, "vehicle") as normal:
        time.sleep(0.2)
        acks = [_ingest(flooder, codec.encode(IngestBatch(_patches(f"flood-{i}", "flooder"))),
                        client="flooder") for i in range(3 * BURST)]
        throttled = [a for a in acks if a.error and a.error.startswith(THROTTLED)]
        assert len(throttled) >= BURST  # over its burst, refused at once
        ok = _ingest(normal, codec.encode(IngestBatch(_patches("normal-0", "veh-n"))),
                     client="veh-n")
        assert ok is not None and ok.error is None  # another vehicle is admitted meanwhile
    assert _stats(fleet)["throttled"] >= len(throttled)


def test_meshed_secure_routers_carry_a_role_s_work_and_its_limits(fleet):
    """A second router meshed to the first over mTLS (its router certificate): a vehicle on it
    reaches the shard behind the first; a localizer on it still cannot ingest."""
    from common.bus import free_tcp_port

    port = free_tcp_port()
    second = f"tls/127.0.0.1:{port}"
    env = dict(os.environ, ROADMAP_BUS__TLS_DIR=str(fleet["certs"]))
    router_b = spawn("router", "--listen", second, "--peer", fleet["endpoint"], env=env)
    try:
        assert wait_for_tcp("127.0.0.1", port, 15.0)
        bus_b = BusConfig(connect=[second], tls_dir=str(fleet["certs"]))
        with open_session(bus_b, "vehicle") as veh, open_session(bus_b, "localizer") as loc:
            deadline = time.monotonic() + 15
            while not list(veh.liveliness().get(keys.alive("merger", "s0"), timeout=1.0)):
                assert time.monotonic() < deadline, "the shard is not seen through the mesh"
                time.sleep(0.2)
            ack = _ingest(veh, codec.encode(IngestBatch(_patches("via-b", "veh-b"))),
                          client="veh-b")
            assert ack is not None and ack.error is None
            payload = codec.encode(IngestBatch(_patches("loc-via-b")))
            assert _replies(loc, keys.ingest(0), payload=payload) == []
    finally:
        _stop(router_b)
