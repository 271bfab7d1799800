"""On-disk outbox of the vehicle: every GridPatch is durable here before it is sent.

Layout under the state directory:
    outbox/<patch_id>.patch   one encoded GridPatch (or SparsePatch) per file, written tmp +
                              fsync + rename
    acked.log                 "<patch_id> <accepted|duplicate>" lines, appended + fsynced on ack
    progress.json             {"traversal", "sealed": number of patch sequence numbers written}

A patch file is deleted only after its ack is in acked.log. A restarted vehicle re-maps the drive
deterministically (same patch ids) and skips the sequence numbers below `sealed`: those patches
are already in the outbox or acked. Counters come from acked.log (unique ids), so a crash between
logging an ack and deleting the file counts nothing twice."""

import json
import logging
import os
import re
from pathlib import Path

from common import codec
from common.errors import CodecError
from common.messages import ACCEPTED, GridPatch, SparsePatch

logger = logging.getLogger(__name__)

SAFE_ID = re.compile(r"^[A-Za-z0-9._,=+-]{1,200}$")
SUFFIX = ".patch"


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """tmp file + fsync + rename + fsync of the directory: the file is whole or absent."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


class Outbox:
    def __init__(self, state_dir: str | os.PathLike):
        self.root = Path(state_dir)
        self.dir = self.root / "outbox"
        self.dir.mkdir(parents=True, exist_ok=True)
        for stale in self.dir.glob("*.tmp"):  # a crash mid-write leaves only tmp files
            stale.unlink()
        self._acked_path = self.root / "acked.log"
        self._acked = self._read_acked()

    # -- patches -----------------------------------------------------------------------------

    def put(self, patches: list[GridPatch | SparsePatch]) -> None:
        for p in patches:
            if p.patch_id in self._acked:
                continue  # acked in an earlier run: never re-send
            write_atomic(self._path(p.patch_id), codec.encode(p))

    def pending(self) -> list[str]:
        """Patch ids waiting for an ack, oldest first."""
        files = sorted(self.dir.glob("*" + SUFFIX), key=lambda f: f.stat().st_mtime_ns)
        return [f.name[: -len(SUFFIX)] for f in files]

    def load(self, patch_id: str) -> GridPatch | SparsePatch:
        patch = codec.decode(self._path(patch_id).read_bytes())
        if not isinstance(patch, GridPatch | SparsePatch):
            raise CodecError(f"outbox {patch_id}: expected a GridPatch or SparsePatch")
        return patch

    def ack(self, results: dict[str, str]) -> None:
        """Log the acks durably, then delete the acked patches from the outbox."""
        lines = [f"{pid} {status}\n" for pid, status in results.items()]
        with open(self._acked_path, "a+b") as f:
            f.seek(0, os.SEEK_END)
            if f.tell() and (f.seek(-1, os.SEEK_END), f.read(1))[1] != b"\n":
                lines.insert(0, "\n")  # finish a line torn by a crash
            f.write("".join(lines).encode())
            f.flush()
            os.fsync(f.fileno())
        for pid, status in results.items():
            self._acked.setdefault(pid, status)
            self._path(pid).unlink(missing_ok=True)

    def counts(self) -> dict[str, int]:
        """Unique acked patches, split by the first status the shard gave each."""
        accepted = sum(1 for s in self._acked.values() if s == ACCEPTED)
        return {
            "acked": len(self._acked),
            "accepted": accepted,
            "duplicates": len(self._acked) - accepted,
        }

    # -- progress ----------------------------------------------------------------------------

    def sealed(self, traversal: str) -> int:
        """Patch sequence numbers already written for this traversal (0 on a fresh state)."""
        try:
            progress = json.loads((self.root / "progress.json").read_text())
        except (OSError, ValueError):
            return 0
        return int(progress.get("sealed", 0)) if progress.get("traversal") == traversal else 0

    def set_sealed(self, traversal: str, sealed: int) -> None:
        data = json.dumps({"traversal": traversal, "sealed": int(sealed)}).encode()
        write_atomic(self.root / "progress.json", data)

    # -- internals ---------------------------------------------------------------------------

    def _path(self, patch_id: str) -> Path:
        if not SAFE_ID.match(patch_id):
            raise ValueError(f"patch id {patch_id!r} is not a safe file name")
        return self.dir / (patch_id + SUFFIX)

    def acked_ids(self) -> set[str]:
        """Ids of every patch a shard has acked (this run or an earlier one)."""
        return set(self._acked)

    def _read_acked(self) -> dict[str, str]:
        acked: dict[str, str] = {}
        try:
            text = self._acked_path.read_text()
        except OSError:
            return acked
        for line in text.splitlines():
            parts = line.split()
            if len(parts) == 2:  # a torn last line (crash mid-append) is ignored
                acked.setdefault(parts[0], parts[1])
        return acked
