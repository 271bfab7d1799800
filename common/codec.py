"""Strict msgpack codec for the wire messages: encode(msg) -> bytes, decode(bytes) -> msg.

Envelope {"v": 1, "type": <name>, "body": {...}}; arrays as {"dtype", "shape", "data"} little
endian. Anything unexpected raises CodecError naming what was expected. No pickle anywhere.

Departure from DESIGN.md (Wire format), on purpose: a GridPatch goes out with its cells and
votes packed (`packed`: {codec, n, data}, see pack_cells_votes) instead of the two raw arrays,
16 -> about 1 byte per cell: the upload is what a vehicle pays for on a cellular link, and
the bytes every router forwards and every shard writes and fsyncs before its ack. The decoder
still takes the DESIGN form (`cells` + `votes` arrays); `encode(..., packed=False)` writes it.

Version 2 of the patch form, added beside it (issue #68): SparsePatch / SparseBatch, the
"sparse/1" form of common/sparse.py, about 1 % of the packed form's bytes; GridPatch and
IngestBatch decode (and apply) as before."""

import lzma
import math
import zlib
from typing import Any

import msgpack
import numpy as np

from common import sparse
from common.classes import NUM_CLASSES
from common.errors import CodecError
from common.grid import CELLS_PER_TILE
from common.messages import (
    GridPatch,
    IngestAck,
    IngestBatch,
    Pose,
    SparseBatch,
    SparsePatch,
    Stats,
    Tile,
    patch_id,
)

VERSION = 1
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_BATCH_PATCHES = 4096
MAX_ID_CHARS = 256
PACKED_CODEC = "zlib-dcv/1"
CELL_BYTES = 4 + 2 * NUM_CLASSES  # a cell unpacked: uint32 index + uint16 votes per class
MAX_MESSAGE_CELLS = MAX_MESSAGE_BYTES // CELL_BYTES  # what one message of raw arrays can carry


# -- arrays ------------------------------------------------------------------------------------


def pack_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    return {"dtype": dtype.str, "shape": list(a.shape), "data": a.astype(dtype).tobytes()}


def unpack_array(
    obj: Any, what: str, dtype: str, ndim: int, width: int | None = None
) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise CodecError(f"{what}: expected an array map {{dtype, shape, data}}")
    if obj["dtype"] != dtype:
        raise CodecError(f"{what}: expected dtype {dtype}, got {obj['dtype']!r}")
    shape = obj["shape"]
    if not isinstance(shape, list) or len(shape) != ndim or not all(
        isinstance(n, int) and n >= 0 for n in shape
    ):
        raise CodecError(f"{what}: expected a shape of {ndim} non-negative ints, got {shape!r}")
    if width is not None and shape[-1] != width:
        raise CodecError(f"{what}: expected last dimension {width}, got {shape[-1]}")
    data = obj["data"]
    itemsize = np.dtype(dtype).itemsize
    if not isinstance(data, bytes) or len(data) != itemsize * math.prod(shape):
        raise CodecError(f"{what}: data length does not match shape {shape} of {dtype}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


# -- packed cells + votes ----------------------------------------------------------------------


def pack_cells_votes(cells: np.ndarray, votes: np.ndarray) -> bytes:
    """PACKED_CODEC: zlib (level 1) of the cell index deltas (<u4, the first against 0) followed
    by the votes class by class, as uint8 when every count fits (else <u2; the length tells).
    Sorted cells make the deltas mostly 1 and a class column mostly zeros: ~1 byte per cell
    instead of 16, ~40 ns per cell to pack, ~15 to unpack."""
    deltas = np.diff(np.asarray(cells, dtype=np.int64), prepend=0).astype("<u4")
    votes = np.asarray(votes)
    narrow = not votes.size or int(votes.max()) <= 255
    columns = votes.astype(np.uint8 if narrow else "<u2").T
    return zlib.compress(deltas.tobytes() + columns.tobytes(), 1)


def unpack_cells_votes(data: bytes, n: int, what: str = "packed cells") -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """(cells uint32 [n], votes uint8 or uint16 [n, NUM_CLASSES]) from pack_cells_votes' bytes,
    checked: exactly n cells' worth of data (never inflates past it), cells sorted, unique, in
    the tile."""
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(data, n * CELL_BYTES)
    except zlib.error as exc:
        raise CodecError(f"{what}: not {PACKED_CODEC} data: {exc}") from exc
    width = (len(raw) - 4 * n) // (n * NUM_CLASSES) if n else 1
    if (len(raw) != n * (4 + NUM_CLASSES * width) or width not in (1, 2)
            or inflate.unconsumed_tail or not inflate.eof or inflate.unused_data):
        raise CodecError(f"{what}: data does not hold exactly {n} cells")
    deltas = np.frombuffer(raw, dtype="<u4", count=n)
    if n > 1 and int(deltas[1:].min()) == 0:
        raise CodecError(f"{what}: cells must be sorted and unique")
    if n and int(deltas.sum(dtype=np.uint64)) >= CELLS_PER_TILE:  # the last cell, no wrap
        raise CodecError(f"{what}: cell index out of range [0, {CELLS_PER_TILE})")
    dtype = np.uint8 if width == 1 else np.dtype("<u2")
    votes = np.frombuffer(raw, dtype=dtype, offset=4 * n).reshape(NUM_CLASSES, n).T
    return np.cumsum(deltas, dtype=np.uint32), votes


# -- field checks -------------------------------------------------------------------------------


def _field(body: dict, name: str, types, what: str):
    if name not in body:
        raise CodecError(f"{what}: missing field {name!r}")
    value = body[name]
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in _tuple(types)):
        raise CodecError(f"{what}: field {name!r} must be {_type_names(types)}")
    if isinstance(value, float) and not math.isfinite(value):
        raise CodecError(f"{what}: field {name!r} must be finite")
    if isinstance(value, str) and len(value) > MAX_ID_CHARS:
        raise CodecError(f"{what}: field {name!r} longer than {MAX_ID_CHARS} characters")
    return value


def _tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def _type_names(types) -> str:
    return " or ".join(t.__name__ for t in _tuple(types))


def _tile_field(body: dict, what: str) -> tuple[int, int]:
    tile = _field(body, "tile", list, what)
    if len(tile) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in tile):
        raise CodecError(f"{what}: field 'tile' must be [tx, ty] integers")
    return int(tile[0]), int(tile[1])


# -- per-type body encoders/decoders ------------------------------------------------------------


def _enc_patch(p: GridPatch, packed: bool = True) -> dict:
    body = {
        "patch_id": p.patch_id,
        "vehicle": p.vehicle,
        "tile": [int(p.tile[0]), int(p.tile[1])],
        "t_first_ns": int(p.t_first_ns),
        "t_last_ns": int(p.t_last_ns),
        "traversal": p.traversal,
    }
    if packed:
        body["packed"] = {"codec": PACKED_CODEC, "n": int(len(p.cells)),
                          "data": pack_cells_votes(p.cells, p.votes)}
    else:
        body["cells"] = pack_array(np.asarray(p.cells, dtype="<u4"))
        body["votes"] = pack_array(np.asarray(p.votes, dtype="<u2"))
    return body


def _packed_cells(body: dict) -> int:
    """Cells a patch body declares in packed form (0 for the raw-array form or a malformed one:
    that fails in _dec_patch)."""
    packed = body.get("packed") if isinstance(body, dict) else None
    n = packed.get("n") if isinstance(packed, dict) else None
    return n if isinstance(n, int) and n > 0 else 0


def _dec_cells_votes(body: dict, what: str) -> tuple[np.ndarray, np.ndarray, bytes | None]:
    if "packed" not in body:
        cells = unpack_array(body.get("cells"), f"{what}.cells", "<u4", 1)
        votes = unpack_array(body.get("votes"), f"{what}.votes", "<u2", 2, NUM_CLASSES)
        if votes.shape[0] != cells.shape[0]:
            raise CodecError(f"{what}: votes must have one row per cell ({cells.shape[0]})")
        if cells.size and int(cells.max()) >= CELLS_PER_TILE:
            raise CodecError(f"{what}: cell index out of range [0, {CELLS_PER_TILE})")
        if cells.size > 1 and not np.all(np.diff(cells.astype(np.int64)) > 0):
            raise CodecError(f"{what}: cells must be sorted and unique")
        return cells, votes, None
    if "cells" in body or "votes" in body:
        raise CodecError(f"{what}: either packed or cells + votes, not both")
    packed = body["packed"]
    if not isinstance(packed, dict) or set(packed) != {"codec", "n", "data"}:
        raise CodecError(f"{what}.packed: expected a map {{codec, n, data}}")
    if packed["codec"] != PACKED_CODEC:
        raise CodecError(f"{what}.packed: unknown codec {packed['codec']!r}, expected "
                         f"{PACKED_CODEC}")
    n, data = packed["n"], packed["data"]
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= CELLS_PER_TILE:
        raise CodecError(f"{what}.packed: n must be an int in [0, {CELLS_PER_TILE}]")
    if not isinstance(data, bytes):
        raise CodecError(f"{what}.packed: data must be bytes")
    cells, votes = unpack_cells_votes(data, n, f"{what}.packed")
    return cells, votes, data


def _dec_patch(body: dict) -> GridPatch:
    what = "GridPatch"
    if not isinstance(body, dict):
        raise CodecError(f"{what}: body must be a map")
    cells, votes, packed = _dec_cells_votes(body, what)
    t_first = _field(body, "t_first_ns", int, what)
    t_last = _field(body, "t_last_ns", int, what)
    if t_last < t_first:
        raise CodecError(f"{what}: t_last_ns before t_first_ns")
    patch_id = _field(body, "patch_id", str, what)
    if not patch_id:
        raise CodecError(f"{what}: patch_id must not be empty")
    return GridPatch(
        patch_id=patch_id,
        vehicle=_field(body, "vehicle", str, what),
        tile=_tile_field(body, what),
        cells=cells,
        votes=votes,
        t_first_ns=t_first,
        t_last_ns=t_last,
        traversal=_field(body, "traversal", str, what),
        packed=packed,
    )


def _enc_batch(b: IngestBatch, packed: bool = True) -> dict:
    return {"patches": [_enc_patch(p, packed) for p in b.patches]}


def _dec_batch(body: dict) -> IngestBatch:
    patches = _field(body, "patches", list, "IngestBatch")
    if len(patches) > MAX_BATCH_PATCHES:
        raise CodecError(f"IngestBatch: at most {MAX_BATCH_PATCHES} patches, got {len(patches)}")
    declared = sum(_packed_cells(p) for p in patches)
    if declared > MAX_MESSAGE_CELLS:  # checked before inflating anything
        raise CodecError(f"IngestBatch: at most {MAX_MESSAGE_CELLS} cells, got {declared}")
    return IngestBatch([_dec_patch(p) for p in patches])


# -- sparse patches (common/sparse.py) ----------------------------------------------------------
# A SparseBatch's body is {"compression": "zlib" | "lzma", "size", "data"}: its patches,
# compressed as one by whichever compressor gives fewer bytes (raw LZMA2 with the filters
# below, or zlib level 9); "size" is the uncompressed length: decompression stops there and
# must end exactly there. Uncompressed, a msgpack list of groups, one per run of patches of one
# vehicle, traversal and form: {"vehicle", "traversal", "form", "patches": [[id, tx, ty,
# t_first_ns, t_last_ns - t_first_ns, data], ...]}, where id is the patch id, or the seq of an
# id made by common.messages.patch_id (so what a batch's patches share is written once).

SPARSE_COMPRESSIONS = ("zlib", "lzma")
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9}]
_GROUP_FIELDS = {"vehicle", "traversal", "form", "patches"}


def _enc_sparse_patch(p: SparsePatch) -> dict:
    return {
        "patch_id": p.patch_id,
        "vehicle": p.vehicle,
        "tile": [int(p.tile[0]), int(p.tile[1])],
        "t_first_ns": int(p.t_first_ns),
        "t_last_ns": int(p.t_last_ns),
        "traversal": p.traversal,
        "form": p.form,
        "data": bytes(p.data),
    }


def _dec_sparse_patch(body: dict) -> SparsePatch:
    what = "SparsePatch"
    if not isinstance(body, dict):
        raise CodecError(f"{what}: body must be a map")
    return _checked_sparse(SparsePatch(
        patch_id=_field(body, "patch_id", str, what), vehicle=_field(body, "vehicle", str, what),
        tile=_tile_field(body, what), t_first_ns=_field(body, "t_first_ns", int, what),
        t_last_ns=_field(body, "t_last_ns", int, what),
        traversal=_field(body, "traversal", str, what), data=_field(body, "data", bytes, what),
        form=_field(body, "form", str, what)), what)


def _checked_sparse(p: SparsePatch, what: str) -> SparsePatch:
    if p.form != sparse.FORM:
        raise CodecError(f"{what}: unknown form {p.form!r}, expected {sparse.FORM}")
    if not p.patch_id:
        raise CodecError(f"{what}: patch_id must not be empty")
    if p.t_last_ns < p.t_first_ns:
        raise CodecError(f"{what}: t_last_ns before t_first_ns")
    sparse.unpack(p.data, f"{what}.data")  # strict: the payload must parse whole
    return p


def _short_id(p: SparsePatch) -> int | str:
    seq = p.patch_id.rsplit(".", 1)[-1]
    if seq.isdigit() and patch_id(p.vehicle, p.traversal, p.tile, int(seq)) == p.patch_id:
        return int(seq)
    return p.patch_id


def _enc_sparse_batch(b: SparseBatch) -> dict:
    groups: list[dict] = []
    for p in b.patches:
        if not groups or (groups[-1]["vehicle"], groups[-1]["traversal"], groups[-1]["form"]) != (
                p.vehicle, p.traversal, p.form):
            groups.append({"vehicle": p.vehicle, "traversal": p.traversal, "form": p.form,
                           "patches": []})
        groups[-1]["patches"].append([_short_id(p), int(p.tile[0]), int(p.tile[1]),
                                      int(p.t_first_ns), int(p.t_last_ns - p.t_first_ns),
                                      bytes(p.data)])
    raw = msgpack.packb(groups, use_bin_type=True)
    packed = {"zlib": zlib.compress(raw, 9),
              "lzma": lzma.compress(raw, format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)}
    name = min(SPARSE_COMPRESSIONS, key=lambda k: len(packed[k]))
    return {"compression": name, "size": len(raw), "data": packed[name]}


def _dec_sparse_batch(body: dict) -> SparseBatch:
    what = "SparseBatch"
    name = _field(body, "compression", str, what)
    if name not in SPARSE_COMPRESSIONS:
        raise CodecError(f"{what}: unknown compression {name!r}, expected one of "
                         f"{list(SPARSE_COMPRESSIONS)}")
    size = _field(body, "size", int, what)
    if not 0 <= size <= MAX_MESSAGE_BYTES:
        raise CodecError(f"{what}: size must be in [0, {MAX_MESSAGE_BYTES}]")
    raw = _decompressed(name, _field(body, "data", bytes, what), size, what)
    try:
        groups = msgpack.unpackb(raw, raw=False, strict_map_key=True, max_bin_len=size)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise CodecError(f"{what}: not a msgpack list of patch groups: {exc}") from exc
    if not isinstance(groups, list):
        raise CodecError(f"{what}: expected a list of patch groups")
    patches = [p for g in groups for p in _dec_sparse_group(g, what)]
    if len(patches) > MAX_BATCH_PATCHES:
        raise CodecError(f"{what}: at most {MAX_BATCH_PATCHES} patches, got {len(patches)}")
    return SparseBatch(patches)


def _dec_sparse_group(group, what: str) -> list[SparsePatch]:
    if not isinstance(group, dict) or set(group) != _GROUP_FIELDS:
        raise CodecError(f"{what}: a group must be a map {{{', '.join(sorted(_GROUP_FIELDS))}}}")
    vehicle, traversal = _field(group, "vehicle", str, what), _field(group, "traversal", str, what)
    form, rows = _field(group, "form", str, what), _field(group, "patches", list, what)
    if len(rows) > MAX_BATCH_PATCHES:
        raise CodecError(f"{what}: at most {MAX_BATCH_PATCHES} patches")
    out = []
    for row in rows:
        if not (isinstance(row, list) and len(row) == 6
                and isinstance(row[0], int | str) and not isinstance(row[0], bool)
                and all(isinstance(v, int) and not isinstance(v, bool) for v in row[1:5])
                and isinstance(row[5], bytes) and row[4] >= 0):
            raise CodecError(f"{what}: a patch must be [id or seq, tx, ty, t_first_ns, "
                             f"t_last_ns - t_first_ns >= 0, data]")
        pid = patch_id(vehicle, traversal, (row[1], row[2]), row[0]) if isinstance(
            row[0], int) and row[0] >= 0 else row[0]
        if not isinstance(pid, str) or len(pid) > MAX_ID_CHARS:
            raise CodecError(f"{what}: patch id must be a string of at most {MAX_ID_CHARS} "
                             "characters or a seq >= 0")
        out.append(_checked_sparse(SparsePatch(
            patch_id=pid, vehicle=vehicle, tile=(row[1], row[2]), t_first_ns=row[3],
            t_last_ns=row[3] + row[4], traversal=traversal, data=row[5], form=form), what))
    return out


def _decompressed(name: str, data: bytes, size: int, what: str) -> bytes:
    """Exactly `size` bytes out of `data`, never more (no bombs), with nothing left over."""
    try:
        if name == "zlib":
            inflate = zlib.decompressobj()
            raw = inflate.decompress(data, size)
            whole = inflate.eof and not inflate.unconsumed_tail and not inflate.unused_data
        else:
            inflate = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
            raw = inflate.decompress(data, size)
            whole = inflate.eof and not inflate.unused_data
    except (zlib.error, lzma.LZMAError) as exc:
        raise CodecError(f"{what}: not {name} data: {exc}") from exc
    if len(raw) != size or not whole:
        raise CodecError(f"{what}: data does not hold exactly {size} bytes of {name}")
    return raw


def _enc_ack(a: IngestAck) -> dict:
    return {"results": dict(a.results), "error": a.error}


def _dec_ack(body: dict) -> IngestAck:
    results = _field(body, "results", dict, "IngestAck")
    for k, v in results.items():
        if not isinstance(k, str) or v not in ("accepted", "duplicate"):
            raise CodecError("IngestAck: results must map patch ids to accepted|duplicate")
    error = body.get("error")
    if error is not None and not isinstance(error, str):
        raise CodecError("IngestAck: error must be a string or nil")
    return IngestAck(results=results, error=error)


def _enc_tile(t: Tile) -> dict:
    return {
        "tile": [int(t.tile[0]), int(t.tile[1])],
        "version": int(t.version),
        "codec": t.codec,
        "data": bytes(t.data),
        "classes": [int(c) for c in t.classes],
    }


def _dec_tile(body: dict) -> Tile:
    what = "Tile"
    classes = _field(body, "classes", list, what)
    if not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c < 256 for c in classes):
        raise CodecError(f"{what}: classes must be uint8 integers")
    version = _field(body, "version", int, what)
    if version < 0:
        raise CodecError(f"{what}: version must be >= 0")
    return Tile(
        tile=_tile_field(body, what),
        version=version,
        codec=_field(body, "codec", str, what),
        data=_field(body, "data", bytes, what),
        classes=classes,
    )


def _enc_pose(p: Pose) -> dict:
    return {
        "vehicle": p.vehicle,
        "t_ns": int(p.t_ns),
        "x": float(p.x),
        "y": float(p.y),
        "yaw": float(p.yaw),
        "cov": pack_array(np.asarray(p.cov, dtype="<f8").reshape(3, 3)),
        "ok": bool(p.ok),
    }


def _dec_pose(body: dict) -> Pose:
    what = "Pose"
    cov = unpack_array(body.get("cov"), f"{what}.cov", "<f8", 2, 3)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise CodecError(f"{what}: cov must be a finite 3x3 float64 matrix")
    return Pose(
        vehicle=_field(body, "vehicle", str, what),
        t_ns=_field(body, "t_ns", int, what),
        x=_field(body, "x", float, what),
        y=_field(body, "y", float, what),
        yaw=_field(body, "yaw", float, what),
        cov=cov,
        ok=_field(body, "ok", bool, what),
    )


def _enc_stats(s: Stats) -> dict:
    return {"role": s.role, "ident": s.ident, "counters": dict(s.counters)}


def _dec_stats(body: dict) -> Stats:
    counters = _field(body, "counters", dict, "Stats")
    for k, v in counters.items():
        if not isinstance(k, str) or not isinstance(v, int | float | str) or (
                isinstance(v, float) and not math.isfinite(v)):
            raise CodecError("Stats: counters must map names to ints, finite floats or strings")
    return Stats(
        role=_field(body, "role", str, "Stats"),
        ident=_field(body, "ident", str, "Stats"),
        counters=counters,
    )


_CODECS = {
    GridPatch: ("GridPatch", _enc_patch, _dec_patch),
    IngestBatch: ("IngestBatch", _enc_batch, _dec_batch),
    SparsePatch: ("SparsePatch", _enc_sparse_patch, _dec_sparse_patch),
    SparseBatch: ("SparseBatch", _enc_sparse_batch, _dec_sparse_batch),
    IngestAck: ("IngestAck", _enc_ack, _dec_ack),
    Tile: ("Tile", _enc_tile, _dec_tile),
    Pose: ("Pose", _enc_pose, _dec_pose),
    Stats: ("Stats", _enc_stats, _dec_stats),
}
_DECODERS = {name: dec for name, _, dec in _CODECS.values()}


def encode(msg, *, packed: bool = True) -> bytes:
    """Message -> bytes; `packed=False` writes grid patches as DESIGN.md's raw arrays."""
    try:
        name, enc, _ = _CODECS[type(msg)]
    except KeyError as exc:
        raise CodecError(f"cannot encode {type(msg).__name__}") from exc
    body = enc(msg, packed) if enc in (_enc_patch, _enc_batch) else enc(msg)
    return msgpack.packb({"v": VERSION, "type": name, "body": body}, use_bin_type=True)


def decode(data: bytes, expect: type | None = None):
    """Bytes -> message; with `expect`, also check the message type."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise CodecError(f"message larger than {MAX_MESSAGE_BYTES} bytes")
    try:
        env = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise CodecError(f"not a msgpack envelope {{v, type, body}}: {exc}") from exc
    if not isinstance(env, dict) or set(env) != {"v", "type", "body"}:
        raise CodecError("expected an envelope map with exactly {v, type, body}")
    if env["v"] != VERSION:
        raise CodecError(f"unsupported version {env['v']!r}, expected {VERSION}")
    if not isinstance(env["type"], str) or env["type"] not in _DECODERS:
        raise CodecError(
            f"unknown message type {env['type']!r}, expected one of {sorted(_DECODERS)}"
        )
    if expect is not None and env["type"] != _CODECS[expect][0]:
        raise CodecError(f"expected a {_CODECS[expect][0]}, got {env['type']}")
    if not isinstance(env["body"], dict):
        raise CodecError(f"{env['type']}: body must be a map")
    return _DECODERS[env["type"]](env["body"])
