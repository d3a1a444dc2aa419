"""TensorBoard event files, written synchronously so that a checkpoint is never ahead of them.

A module apart: the loop imports it only with ``tensorboard=true``, because tensorboardX
takes 0.2 s to import and loads numpy, which the JAX-free outputs of `coherent_jax.run.outputs`
(on the path of ``--help``, bad input and dry runs) must not.

tensorboardX's ``SummaryWriter`` hands events to a background thread through a queue,
and its ``flush()`` flushes the file without waiting for that queue. A run killed just
after writing its checkpoint could then lose the scalars of iterations the checkpoint
covers, and the resumed run, which starts past the checkpoint, never writes them again.

`EventWriter` writes each iteration's scalars itself, before the loop writes a
checkpoint: one unbuffered ``write`` of the iteration's records, so that what a killed
run leaves is whole records. An event file is a sequence of TFRecords,

    uint64 length | uint32 masked_crc32c(length) | Event (protobuf) | uint32 masked_crc32c(Event),

little-endian, with CRC-32C (Castagnoli) masked as ``((c >> 15 | c << 17) + 0xa282ead8) mod 2^32``.
The events and the CRC come from tensorboardX; the framing and the timing are ours.

A resumed run opens a new file whose first events are the file version and a
``SessionLog.START`` at ``purge_step``: TensorBoard then drops the events of earlier
files at steps ``>= purge_step``, those a killed run wrote past its checkpoint.
"""

from __future__ import annotations

import os
import socket
import struct
import time
from pathlib import Path

from tensorboardX.proto.event_pb2 import Event, SessionLog
from tensorboardX.proto.summary_pb2 import Summary
from tensorboardX.record_writer import masked_crc32c


class EventWriter:
    """One event file in `logdir`: scalars per step (env steps), on disk when `add_scalars` returns."""

    def __init__(self, logdir: Path | str, purge_step: int | None = None):
        logdir = Path(logdir)
        logdir.mkdir(parents=True, exist_ok=True)
        # time_ns sorts after tensorboardX's whole seconds of the same second ('.' < digits),
        # so TensorBoard reads a resumed run's file after the killed run's.
        name = f"events.out.tfevents.{time.time_ns()}.{socket.gethostname()}.{os.getpid()}"
        self.path = logdir / name
        self._file = open(self.path, "xb", buffering=0)
        now = time.time()
        first = [Event(wall_time=now, file_version="brain.Event:2")]
        if purge_step is not None:
            start = SessionLog(status=SessionLog.START)
            first.append(Event(wall_time=now, step=int(purge_step), session_log=start))
        self._write(first)

    def add_scalars(self, scalars: dict[str, float], step: int) -> None:
        """One event per scalar at `step`, all in one write."""
        now = time.time()
        values = [Summary.Value(tag=k, simple_value=v) for k, v in scalars.items()]
        events = [Event(wall_time=now, step=int(step), summary=Summary(value=[v])) for v in values]
        self._write(events)

    def _write(self, events) -> None:
        records = []
        for event in events:
            data = event.SerializeToString()
            header = struct.pack("<Q", len(data))
            records += [header, struct.pack("<I", masked_crc32c(header))]
            records += [data, struct.pack("<I", masked_crc32c(data))]
        blob = memoryview(b"".join(records))
        while blob:  # a raw write may be partial
            blob = blob[self._file.write(blob) :]

    def close(self) -> None:
        self._file.close()
