"""Hostile wire input for the fuzz tests: valid messages of every type, and hypothesis
strategies that mutate them (truncate, flip, splice, swap a field for any msgpack value) or
build msgpack from scratch (deep nesting, huge declared counts, NaN)."""

import struct
import zlib

import msgpack
import numpy as np
from hypothesis import strategies as st

from common import codec
from common.classes import NUM_CLASSES
from common.messages import GridPatch, IngestAck, IngestBatch, Pose, Stats, Tile


def sample_patch(i: int = 0, n: int = 40, vehicle: str = "veh-0") -> GridPatch:
    rng = np.random.default_rng(i)
    cells = np.sort(rng.choice(512 * 512, n, replace=False)).astype(np.uint32)
    votes = rng.integers(0, 9, (n, NUM_CLASSES)).astype(np.uint16)
    return GridPatch(patch_id=f"{vehicle}/t{i}/{i}", vehicle=vehicle, tile=(i % 3, -1),
                     cells=cells, votes=votes, t_first_ns=10**12 + i, t_last_ns=10**12 + i + 5,
                     traversal=f"t{i}")


def sample_messages() -> list:
    return [
        IngestBatch([sample_patch(0), sample_patch(1)]),
        sample_patch(2),
        IngestAck(results={"a": "accepted", "b": "duplicate"}),
        IngestAck(error="bad batch"),
        Tile(tile=(3, -4), version=7, codec="contour/2", data=b"RMC2\x00abc"),
        Pose("car", 123, 1.5, -2.0, 0.1, np.eye(3), True),
        Stats("merger", "s0", {"patches_applied": 3, "digest": "ab"}),
    ]


VALID_BATCHES = [codec.encode(IngestBatch([sample_patch(0), sample_patch(1)])),
                 codec.encode(IngestBatch([sample_patch(3)]), packed=False)]
VALID = [codec.encode(m) for m in sample_messages()] + VALID_BATCHES

# any msgpack value: what a hostile sender can put in a field
scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=40),
    st.binary(max_size=64))
values = st.recursive(
    scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                     st.dictionaries(st.text(max_size=8), inner, max_size=5)),
    max_leaves=20)


@st.composite
def mutated(draw, sources=tuple(VALID)) -> bytes:
    """A valid message, then one mutation: truncate, flip bytes, splice, or append."""
    data = bytearray(draw(st.sampled_from(sources)))
    kind = draw(st.sampled_from(["truncate", "flip", "splice", "append"]))
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, len(data) - 1))])
    if kind == "flip":
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] = draw(st.integers(0, 255))
        return bytes(data)
    if kind == "splice":
        i = draw(st.integers(0, len(data)))
        return bytes(data[:i] + draw(st.binary(min_size=1, max_size=16)) + data[i:])
    return bytes(data) + draw(st.binary(min_size=1, max_size=16))


def _set_path(obj, path: list, value):
    """Replace obj at a path of keys/indices (the last one that exists) with value."""
    node = obj
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return obj


def _paths(obj, prefix=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield (*prefix, i)
            yield from _paths(v, (*prefix, i))


@st.composite
def wrong_field(draw, sources=tuple(VALID)) -> bytes:
    """A valid message with one field (anywhere in it: envelope, body, array maps, patches)
    replaced by any msgpack value, or deleted."""
    env = msgpack.unpackb(draw(st.sampled_from(sources)), raw=False)
    paths = list(_paths(env))
    path = list(draw(st.sampled_from(paths)))
    if draw(st.booleans()):
        _set_path(env, path, draw(values))
    else:
        node = env
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]
    return msgpack.packb(env, use_bin_type=True)


def deep_nesting(depth: int) -> bytes:
    """An envelope whose body is [[[...]]] depth levels deep."""
    head = b"\x83" + b"".join(msgpack.packb(x) for x in ("v", 1, "type", "IngestBatch", "body"))
    return head + b"\x91" * depth + b"\xc0"  # fixarray(1) ... nil


def huge_counts() -> list[bytes]:
    """Headers that declare far more elements or bytes than follow."""
    env = b"\x83\xa1v\x01\xa4type\xabIngestBatch\xa4body"
    return [
        b"\xdd" + struct.pack(">I", 2**32 - 1),  # array32 of 4 G elements, no data
        b"\xdf" + struct.pack(">I", 2**32 - 1),  # map32
        b"\xc6" + struct.pack(">I", 2**32 - 1) + b"x" * 16,  # bin32 of 4 GB
        b"\xdb" + struct.pack(">I", 2**32 - 1) + b"x" * 16,  # str32
        env + b"\x81\xa7patches\xdd" + struct.pack(">I", 2**31),  # patches: 2 G elements
        env + b"\x81\xa7patches\xdc\xff\xff" + b"\xc0" * 10,  # 65535 patches, 10 given
    ]


def zlib_bomb_patch(n_cells: int = 1000, inflated: int = 50 << 20) -> bytes:
    """An IngestBatch whose packed patch claims n_cells but inflates to `inflated` bytes."""
    body = codec._enc_patch(sample_patch(5))
    body["packed"] = {"codec": codec.PACKED_CODEC, "n": n_cells,
                      "data": zlib.compress(b"\0" * inflated, 9)}
    env = {"v": 1, "type": "IngestBatch", "body": {"patches": [body]}}
    return msgpack.packb(env, use_bin_type=True)


def nan_pose() -> bytes:
    body = codec._enc_pose(Pose("car", 1, 0.0, 0.0, 0.0, np.eye(3), True))
    body["x"] = float("nan")
    return msgpack.packb({"v": 1, "type": "Pose", "body": body}, use_bin_type=True)


def type_field_array() -> bytes:
    """The escape the issue's one-minute fuzz found: `type` an array (unhashable)."""
    return msgpack.packb({"v": 1, "type": ["IngestBatch"], "body": {}}, use_bin_type=True)
