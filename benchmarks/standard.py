"""The ``standard`` suite: what fidelity to Gymnasium costs, next to EnvPool.

    python -m benchmarks standard [tasks=[halfcheetah,hopper,...]] [envs=[64]]
        [steps=...] [repeats=3] [out=bench_results/physics_standard.json]

For each standard task (Gymnasium's v5 task on native MuJoCo), env count, and thread
count (1, then every core): our `VecEnv` of the Gymnasium task, EnvPool stepping the
same task with the same threads (``pip install -e ".[bench]"``), and the Brax
re-creation (``brax-*``) on the physics ``physics=auto`` picks for it. The three are
timed round-robin in one subprocess per (task, envs, threads), so that they share the
machine's load (`benchmarks.physics` holds the measurement itself).
A bad key or value is one line on stderr and exit status 2, before anything runs.
"""

from __future__ import annotations

import datetime
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import mujoco

from benchmarks import measure, physics
from coherent_jax.config import cli
from coherent_jax.envs.registry import SHORT_NAMES, resolve_physics

# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~20 min (1,174 s measured: 5 tasks x 2 thread counts)"
KEYS: dict[str, cli.Key] = {
    "tasks": cli.Key(
        ["halfcheetah", "hopper", "walker2d", "ant", "humanoid"],
        cli.choice_list(tuple(SHORT_NAMES)),
        "a non-empty list of " + ", ".join(SHORT_NAMES),
        "standard tasks to measure",
    ),
    "envs": cli.Key([64], cli.int_list(1), "a list of integers >= 1, e.g. [16,64]", "env counts"),
    "steps": cli.Key(
        0, cli.int_at_least(0), "an integer >= 0", "env steps per timed call; 0: 10000 / envs (at least 10)"
    ),
    "repeats": cli.Key(3, cli.int_at_least(1), "an integer >= 1", "timed calls per row (median)"),
    "out": cli.Key(
        "bench_results/physics_standard.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings (no training config); `ConfigError` in one line for bad input."""
    return cli.parse_command(items, KEYS, command="the standard suite", config=False)


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict[str, Any]:
    """Env steps/s of each standard task (Gymnasium's, native), its Brax re-creation and EnvPool.

    One process per task, env count and thread count (1, then every core), timing the
    three round-robin so that they share the machine's load: our ``VecEnv`` of the
    Gymnasium task (``native``/``native_all``), EnvPool on the same task with the same
    threads (``envpool``/``envpool_all``), and the Brax re-creation (``brax-*``) on the
    physics ``physics=auto`` picks for it here (native MuJoCo for six of Brax's tasks,
    with the same threads; else MJX, whose threads XLA chooses, measured at 1 only).
    """
    settings = parse(items).settings
    rows = []
    for task in settings["tasks"]:
        brax = f"brax-{task}"
        brax_native = resolve_physics(brax, "auto") == "native"
        for n in settings["envs"]:
            for threads, suffix in ((1, ""), (0, "_all")):
                plan = [("standard", task, "native" + suffix), ("envpool", task, "envpool" + suffix)]
                if brax_native or not suffix:
                    plan.append(("brax", brax, ("native" if brax_native else "mjx") + suffix))
                steps = settings["steps"] or max(10, 10000 // n)
                spec = {"plan": plan, "n": n, "steps": steps, "repeats": settings["repeats"]}
                t0 = time.perf_counter()
                result = physics._spawn(spec)
                took = time.perf_counter() - t0
                if "error" in result:
                    result["rows"] = [{"kind": kind, "error": result["error"]} for kind, _, _ in plan]
                for row in result["rows"]:
                    rows.append({**row, "task": task, "n": n, "threads": threads})
                    status = row.get("error") or f"{row['env_steps_per_s']:,.0f} env steps/s"
                    log(f"  {task:<12} {row['kind']:<8} {n:>5} envs, threads {threads or 'all'}: {status}")
                log(f"  ({took:.0f} s, load average {result.get('load_average')})")
    result = {
        "suite": "standard",
        "settings": settings,
        "rows": rows,
        "load_average": os.getloadavg(),
        "machine": {"cpu_count": os.cpu_count(), "jax": jax.__version__, "mujoco": mujoco.__version__},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    measure.write_json_atomic(Path(settings["out"]), result)
    log(f"wrote {settings['out']}")
    return result


def format_table(result: dict[str, Any]) -> str:
    """Per task, env count and thread count: standard, Brax re-creation and EnvPool, in env steps per
    wall-clock second and per CPU-second of the process."""
    lines = [
        f"standard tasks on {result['machine']['cpu_count']} CPUs (load average at the end "
        + ", ".join(f"{x:.1f}" for x in result["load_average"])
        + ")"
    ]

    def fmt(x):
        return f"{x:>11,.0f}" if x else f"{'-':>11}"

    for key, title in (("env_steps_per_s", "env steps/s"), ("env_steps_per_cpu_s", "env steps per CPU-s")):
        rates = {(r["task"], r["n"], r["threads"], r["kind"]): r.get(key) for r in result["rows"]}
        lines.append(
            f"  {title:<22}{'envs':>6}{'threads':>8}"
            f"{'standard':>11}{'brax':>11}{'envpool':>11}{'std/pool':>10}"
        )
        for task, n, threads in dict.fromkeys((t, n, th) for t, n, th, _ in rates):
            std, pool = rates.get((task, n, threads, "standard")), rates.get((task, n, threads, "envpool"))
            # An MJX re-creation is measured once (XLA picks its threads): shown on both lines.
            brax = rates.get((task, n, threads, "brax")) or rates.get((task, n, 1, "brax"))
            ratio = f"{std / pool:>9.2f}x" if std and pool else f"{'-':>10}"
            lines.append(
                f"  {task:<22}{n:>6}{threads or os.cpu_count():>8}{fmt(std)}{fmt(brax)}{fmt(pool)}{ratio}"
            )
    return "\n".join(lines)
