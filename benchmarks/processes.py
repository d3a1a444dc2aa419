"""The ``processes`` suite: ``python -m benchmarks processes [key=value ...]``.

Processes against devices.

Trains the same run twice on this machine, each as a fresh ``python -m
coherent_jax.train``: once as one process with N host devices
(``--xla_force_host_platform_device_count=N``), once as N processes of one device
each (``distributed=true`` over loopback, gloo collectives). Both use a mesh of N
devices, so both run the same program; the difference is the cost of crossing
process boundaries (gloo over TCP instead of in-process all-reduces, and the
per-iteration agreement on stopping). The figure is each run's training env
steps/s (its ``summary.json``: iterations only, compile and evaluation excluded).

Keys: ``processes`` (N, default 2), ``repeats`` (pairs of runs, alternating which
goes first, default 1; the median is reported), ``out`` (default
``bench_results/processes.json``), and any `coherent_jax.train` key (defaults:
pointmass, 128 envs x 32 steps, 16 iterations, no evaluation or checkpoint). The
JSON also records the load average before and after, for figures taken on a
shared machine.
"""

from __future__ import annotations

import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchmarks import measure
from coherent_jax.config import cli
from coherent_jax.run.rundir import atomic_write

DEFAULTS = [
    "env=pointmass",
    "num_envs=128",
    "unroll_length=32",
    "total_steps=65536",
    "eval_every=0",
    "checkpoint_every=0",
    "progress=false",
    "tensorboard=false",
]
WAIT_S = 3600  # bound on one launch
# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~3 min (163 s measured)"
KEYS = {
    "processes": cli.Key(2, cli.int_at_least(2), "an integer >= 2", "processes of one device each (N)"),
    "repeats": cli.Key(
        1, cli.int_at_least(1), "an integer >= 1", "pairs of runs, alternating which goes first"
    ),
    "out": cli.Key("bench_results/processes.json", cli.output_file, "a writable file path", "the JSON"),
}
# Set per launch by the suite.
FIXED: dict[str, str | None] = {"run_dir": None, "distributed": None, "resume": None}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(args: list[str], run_dir: Path, processes: int, devices: int) -> dict[str, Any]:
    """Trains once (``processes`` processes, ``devices`` host devices each); returns process 0's summary."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    command = [sys.executable, "-m", "coherent_jax.train", *args, f"run_dir={run_dir}"]
    port = _free_port()
    procs = []
    try:
        for i in range(processes):
            extra = {}
            if processes > 1:
                extra = {
                    "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}",
                    "JAX_NUM_PROCESSES": str(processes),
                    "JAX_PROCESS_ID": str(i),
                }
            argv = [*command, "distributed=true"] if processes > 1 else command
            procs.append(subprocess.Popen(argv, env={**env, **extra}, stdout=subprocess.DEVNULL))
        deadline = time.monotonic() + WAIT_S
        statuses = [p.wait(timeout=max(deadline - time.monotonic(), 1)) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=30)
    if any(statuses):
        raise RuntimeError(f"a training process failed (exit statuses {statuses})")
    return json.loads((run_dir / "summary.json").read_text())


# The suite starts training commands of its own: it reads every training key other
# suites ignore (a budget, evaluation, checkpoints), with `DEFAULTS` as its defaults.
IGNORED_KEYS: tuple[str, ...] = ()


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and the training config; `ConfigError` in one line for bad input."""
    return cli.parse_command(
        items, KEYS, command="the processes suite", fixed=FIXED, config_defaults=DEFAULTS
    )


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict[str, Any]:
    """Trains the pairs of runs, writes the JSON to ``out`` atomically, returns it."""
    parsed = parse(items)
    settings, cfg = parsed.settings, parsed.config
    # The user's items replace the defaults they name (the training command refuses a key twice).
    given = {cli.split_item(item)[0] for item in parsed.config_items}
    train_args = [*(d for d in DEFAULTS if cli.split_item(d)[0] not in given), *parsed.config_items]
    n, repeats = settings["processes"], settings["repeats"]
    load_before = os.getloadavg()
    rates: dict[str, list[float]] = {"one_process": [], "processes": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeats):
            order = ["one_process", "processes"] if r % 2 == 0 else ["processes", "one_process"]
            for kind in order:
                run_dir = Path(tmp) / f"{kind}-{r}"
                summary = _launch(
                    train_args, run_dir, 1 if kind == "one_process" else n, n if kind == "one_process" else 1
                )
                rates[kind].append(summary["train_env_steps_per_s"])
    one, many = statistics.median(rates["one_process"]), statistics.median(rates["processes"])
    result = {
        "env": cfg.env,
        "algo": cfg.algo,
        "explore": cfg.explore,
        "num_envs": cfg.num_envs,
        "steps_per_iteration": cfg.steps_per_iteration,
        "iterations": cfg.num_iterations,
        "train_args": train_args,
        "processes": n,
        f"one_process_x_{n}_devices_env_steps_per_s": one,
        f"{n}_processes_x_1_device_env_steps_per_s": many,
        "processes_over_one_process": round(many / one, 3),
        "runs": rates,
        "cpu_count": os.cpu_count(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
    }
    out = Path(settings["out"])
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, (json.dumps(result, indent=2) + "\n").encode())
    log(f"[bench] wrote {out}")
    return result


def format_table(result: dict[str, Any]) -> str:
    """The two layouts' training env steps/s and the load around the measurement."""
    n = result["processes"]
    one = result[f"one_process_x_{n}_devices_env_steps_per_s"]
    many = result[f"{n}_processes_x_1_device_env_steps_per_s"]
    return "\n".join(
        [
            f"1 process x {n} devices: {one:10.0f} env steps/s",
            f"{n} processes x 1 device: {many:10.0f} env steps/s  ({many / one:.2f}x)",
            f"load average {result['load_average_before']} -> {result['load_average_after']}",
        ]
    )
