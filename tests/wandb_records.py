"""Reads the records of an offline W&B run (``RUN_DIR/wandb/offline-run-*/run-<id>.wandb``).

The file is W&B's transaction log: a 7-byte header (``:W&B``, magic 0xBEE1, version)
then LevelDB's log format (32 KiB blocks of chunks, each with a 7-byte header: CRC,
length, type FULL/FIRST/MIDDLE/LAST), each record a protobuf ``Record``. Used by the
tests to check what a run logged without the network.
"""

import json
import struct
import time
from pathlib import Path

_BLOCK = 32 * 1024
_FULL, _LAST = 1, 4


def _raw_records(data: bytes):
    ident, magic, _version = struct.unpack("<4sHB", data[:7])
    assert ident == b":W&B" and magic == 0xBEE1, "not a W&B transaction log"
    pos, chunks = 7, []
    while pos + 7 <= len(data):
        left = _BLOCK - pos % _BLOCK
        _crc, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
        if left < 7 or (kind == 0 and length == 0):  # block trailer / padding
            pos += left
            continue
        chunks.append(data[pos + 7 : pos + 7 + length])
        pos += 7 + length
        if kind in (_FULL, _LAST):
            yield b"".join(chunks)
            chunks = []


def _records(path: Path, timeout_s: float):
    """The records of a finished run. ``run.finish()`` returns before W&B's service has
    written the run's records (the last run of a process may reach its file only when the
    process ends), so this waits, up to `timeout_s`, for the ``exit`` record closing it."""
    from wandb.proto import wandb_internal_pb2 as pb

    deadline = time.monotonic() + timeout_s
    while True:
        records = []
        try:
            for raw in _raw_records(Path(path).read_bytes()):
                rec = pb.Record()
                rec.ParseFromString(raw)
                records.append(rec)
        except Exception:  # noqa: BLE001 - a record being written: read again
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
            continue
        if any(r.WhichOneof("record_type") == "exit" for r in records) or time.monotonic() > deadline:
            return records
        time.sleep(0.1)


def read_run(path: Path, timeout_s: float = 60.0) -> dict:
    """The run's id, group and name, its config, its history rows and its final summary."""
    out = {"id": None, "group": None, "name": None, "config": {}, "history": [], "summary": {}}
    for rec in _records(path, timeout_s):
        kind = rec.WhichOneof("record_type")
        if kind == "run":
            out.update(id=rec.run.run_id, group=rec.run.run_group, name=rec.run.display_name)
            out["config"].update({i.key: json.loads(i.value_json) for i in rec.run.config.update})
        elif kind == "config":
            out["config"].update({i.key: json.loads(i.value_json) for i in rec.config.update})
        elif kind == "history":
            out["history"].append(
                {i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in rec.history.item}
            )
        elif kind == "summary":
            out["summary"].update(
                {i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in rec.summary.update}
            )
    out["config"].pop("_wandb", None)
    return out


def offline_runs(run_dir: Path, expected: int = 1, timeout_s: float = 60.0) -> list[Path]:
    """The transaction logs of ``run_dir``'s offline W&B runs, oldest first.

    W&B's service writes them, and may create one after the process that logged it ended:
    this waits, up to `timeout_s`, until there are at least `expected`.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        found = sorted(Path(run_dir).glob("wandb/offline-run-*/run-*.wandb"))
        if len(found) >= expected or time.monotonic() > deadline:
            return found
        time.sleep(0.1)
