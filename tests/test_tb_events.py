"""The TensorBoard event writer: TFRecord framing checked against a bitwise CRC-32C, events on
disk when a call returns (also when the process is then SIGKILLed), the resume's purge event."""

import subprocess
import sys
import textwrap

from helpers import child_env, crc32c, read_events, tensorboard_scalars

from coherent_jax.run.tb_events import EventWriter


def test_the_reference_crc_has_the_standard_check_value():
    # The CRC-32C catalogue's check value, and RFC 3720's 32 bytes of zeros.
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA


def test_scalars_are_whole_records_on_disk_before_the_writer_is_closed(tmp_path):
    w = EventWriter(tmp_path / "tb")
    w.add_scalars({"train/loss": 0.5, "eval/episode_return": -3.25}, 8)
    w.add_scalars({"train/loss": 0.25}, 16)
    # Read through another handle while the writer is still open: nothing waits in a buffer.
    events = read_events(w.path)
    assert events[0].file_version == "brain.Event:2"
    assert not events[0].HasField("session_log")
    scalars = [(e.step, v.tag, v.simple_value) for e in events[1:] for v in e.summary.value]
    assert scalars == [(8, "train/loss", 0.5), (8, "eval/episode_return", -3.25), (16, "train/loss", 0.25)]
    w.close()
    assert read_events(w.path) == events


def test_a_resumed_writer_starts_a_later_file_with_the_purge_event(tmp_path):
    tb = tmp_path / "tb"
    first = EventWriter(tb)
    first.add_scalars({"x": 1.0}, 8)
    first.add_scalars({"x": 2.0}, 16)
    first.close()
    second = EventWriter(tb, purge_step=9)
    second.add_scalars({"x": 3.0}, 16)
    second.close()
    assert sorted(tb.iterdir()) == [first.path, second.path]
    start = read_events(second.path)[1]
    assert start.step == 9 and start.session_log.status == start.session_log.START
    assert tensorboard_scalars(tb) == {"x": {8: 1.0, 16: 3.0}}
    # A file named as tensorboardX names it (whole seconds), of the same second, sorts first.
    second_s = second.path.name.split(".")[3][:10]
    legacy = tb / f"events.out.tfevents.{second_s}.host"
    assert sorted([legacy.name, second.path.name]) == [legacy.name, second.path.name]


def test_events_written_before_a_sigkill_are_all_in_the_file(tmp_path):
    """The loop writes a checkpoint after an iteration's events: whatever a kill leaves, the
    events of every iteration that returned are there."""
    script = textwrap.dedent(
        f"""
        import os, signal
        from coherent_jax.run.tb_events import EventWriter
        w = EventWriter({str(tmp_path / "tb")!r})
        for step in range(1, 201):
            w.add_scalars({{"a": step * 0.5, "b": -step}}, step)
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], env=child_env(), capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr
    scalars = tensorboard_scalars(tmp_path / "tb")
    assert scalars["a"] == {s: s * 0.5 for s in range(1, 201)}
    assert scalars["b"] == {s: -s for s in range(1, 201)}
