"""What every benchmark suite measures and records: compile and call times, XLA's peak
memory, the machine and its load, and the JSON file the results go to."""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jaxlib

try:
    import resource
except ImportError:  # not on Unix: no peak memory figure
    resource = None


def print_log(msg: str) -> None:
    """The suites' default progress log: stdout, flushed (a suite can run for an hour)."""
    print(msg, flush=True)


def memory(compiled) -> dict[str, int] | None:
    """Peak memory of a compiled program from XLA (None if the backend has none)."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if stats is None:
        return None
    fields = {
        "temp_bytes": "temp_size_in_bytes",
        "argument_bytes": "argument_size_in_bytes",
        "output_bytes": "output_size_in_bytes",
        "alias_bytes": "alias_size_in_bytes",
    }
    out = {k: int(getattr(stats, attr, 0) or 0) for k, attr in fields.items()}
    # Donated (aliased) buffers are counted in both arguments and outputs.
    out["peak_bytes"] = out["temp_bytes"] + out["argument_bytes"] + out["output_bytes"] - out["alias_bytes"]
    return out


def compile_timed(fn, *args):
    """``jax.jit(fn)`` lowered and compiled for ``args``: (compiled, seconds it took)."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def warm_iteration(iteration, state, log, what: str) -> dict[str, Any]:
    """``iteration(state) -> (state, metrics)`` compiled and called once untimed, as a run of
    `time_interleaved`: its ``step``, the ``state`` after the warm-up call, ``compile_s``,
    ``memory``, ``warmup_call_s`` and an empty ``times``. ``what`` names it in the log."""
    log(f"[bench] compiling {what} ...")
    step, compile_s = compile_timed(iteration, state)
    mem = memory(step)
    log(f"[bench]   compiled in {compile_s:.1f} s; peak memory {peak_mb(mem)} MB")
    t0 = time.perf_counter()
    state, _ = jax.block_until_ready(step(state))  # warm-up call, not timed
    return {
        "step": step,
        "state": state,
        "compile_s": compile_s,
        "memory": mem,
        "warmup_call_s": time.perf_counter() - t0,
        "times": [],
    }


def time_calls(compiled, args, repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` calls, each waited for to the end."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return times


def time_interleaved(runs: dict[str, dict], names: Sequence[str], rounds: int, log, on_metrics=None) -> None:
    """Times ``rounds`` calls of each run's compiled ``step`` on its ``state``, in alternating order.

    The order flips every round (A B, B A, ...) so that a change of load on a shared
    machine hits every run alike. Each call's seconds go to ``run["times"]`` and its
    new state to ``run["state"]``; ``on_metrics(name, metrics)`` sees its metrics.
    """
    for i in range(rounds):
        order = list(names) if i % 2 == 0 else list(names)[::-1]
        for name in order:
            run = runs[name]
            t0 = time.perf_counter()
            run["state"], metrics = jax.block_until_ready(run["step"](run["state"]))
            run["times"].append(time.perf_counter() - t0)
            if on_metrics is not None:
                on_metrics(name, metrics)
        log(
            f"[bench] round {i + 1}/{rounds}: "
            + ", ".join(f"{n} {runs[n]['times'][-1]:.3f} s" for n in order)
        )


def machine_line(result: dict[str, Any]) -> str:
    """The software, device, CPU and load of a suite's result, for its table."""
    return (
        f"jax {result['jax_version']} on {result['device']} ({result['cpu']}, {result['cpu_count']} CPUs); "
        f"load average {result['load_average_start']} -> {result['load_average_end']}"
    )


def mb(nbytes: int | None) -> str:
    """Bytes as MB for a table; ``-`` when unknown."""
    return "-" if nbytes is None else f"{nbytes / 2**20:,.1f}"


def peak_mb(mem: dict | None) -> str:
    """The peak of a `memory` record as MB for a table."""
    return mb(peak(mem))


def peak(mem: dict | None) -> int | None:
    """The peak bytes of a `memory` record (None if there is none)."""
    return None if mem is None else mem["peak_bytes"]


def load_average() -> list[float]:
    """The 1, 5 and 15 minute load averages: every figure on a shared machine needs them."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return []


def cpu_model() -> str:
    """The CPU's model name."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def peak_rss_bytes() -> int | None:
    """This process's peak resident memory."""
    if resource is None:
        return None
    try:
        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB
    except OSError:
        return None


def machine() -> dict[str, Any]:
    """When and where a suite ran: time, versions, device, CPU, XLA flags, load at the start."""
    device = jax.devices()[0]
    return {
        "timestamp": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "jax_version": jax.__version__,
        "jaxlib_version": getattr(jaxlib, "__version__", None),
        "device": str(device),
        "platform": device.platform,
        "device_kind": getattr(device, "device_kind", None),
        "device_count": jax.device_count(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_start": load_average(),
    }


def start(suite: str, log) -> tuple[dict[str, Any], float]:
    """A suite's `machine` record and its start time; logs both."""
    info = machine()
    log(
        f"[bench] {suite} suite: jax {info['jax_version']} on {info['platform']} ({info['cpu']}, "
        f"{info['cpu_count']} CPUs), load average {info['load_average_start']}"
    )
    return info, time.perf_counter()


def finish(
    suite: str, info: dict[str, Any], t_start: float, settings: dict, figures: dict, out: str, log
) -> dict[str, Any]:
    """A suite's result (machine, settings, figures, load at the end, wall time), written to ``out``."""
    result = {
        "suite": suite,
        **info,
        "load_average_end": load_average(),
        "settings": settings,
        **figures,
        "wall_s": time.perf_counter() - t_start,
    }
    write_json_atomic(Path(out), result)
    log(f"[bench] wrote {out} ({result['wall_s']:.0f} s)")
    return result


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str):  # numpy / jax scalars
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json_atomic(path: Path, data: dict) -> None:
    """Writes ``data`` to a temporary file beside ``path`` and renames it: never half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)
