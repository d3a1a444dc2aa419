"""The ``gym`` suite: Gymnasium envs stepped on the host, against Gymnasium's own vector env.

    python -m benchmarks gym [envs=[gym:Pendulum-v1,gym:HalfCheetah-v5]] [num_envs=16]
        [steps=2048] [iterations=8] [out=bench_results/gym.json]

For each env, four rows of env steps per second at ``num_envs`` copies, so that the table
says where the time goes:

* ``sync``: Gymnasium's ``SyncVectorEnv`` stepped with random actions drawn beforehand, the
  limit (the envs' own Python and physics, nothing else);
* ``pool``: our host pool (`coherent_jax.envs.host_gym.HostPool`) stepped from Python with
  the same actions: the per-env loop, the observation copies and the autoreset;
* ``vec``: `VecEnv` stepped under one jit (``lax.scan``) with random actions: the pool
  reached through ``jax.pure_callback``, what training's collection pays;
* ``train``: PPO training (``python -m coherent_jax.train``, ``explore=action``), env steps
  per second of training time (collection and updates; compilation and evaluation apart).

The ratio ``train / sync`` is the one the goal is stated in (>= 0.8). Rows of one env are
timed in one process, one after the other; on a shared machine compare them side by side.
"""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import measure
from coherent_jax.config import cli, make_config
from coherent_jax.envs.gym_source import quietly
from coherent_jax.envs.vec_env import VecEnv

# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~3 min (2 envs x 4 rows, compilation included; measured 2026-12-06 under load)"
KEYS: dict[str, cli.Key] = {
    "envs": cli.Key(
        ["gym:Pendulum-v1", "gym:HalfCheetah-v5"],
        lambda text: [t.strip() for t in text.strip("[]").split(",") if t.strip()],
        "a list of gym:ID",
        "Gymnasium envs to measure",
    ),
    "num_envs": cli.Key(16, cli.int_at_least(1), "an integer >= 1", "env copies"),
    "steps": cli.Key(2048, cli.int_at_least(1), "an integer >= 1", "vector steps timed per row but train"),
    "iterations": cli.Key(8, cli.int_at_least(1), "an integer >= 1", "training iterations timed"),
    "out": cli.Key("bench_results/gym.json", cli.output_file, "a writable file path", "where the JSON goes"),
}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings (no training config); `ConfigError` in one line for bad input."""
    return cli.parse_command(items, KEYS, command="the gym suite", config=False)


def _sync(gym_id: str, n: int, actions: np.ndarray, episode_length: int) -> float:
    with quietly():
        envs = gymnasium.vector.SyncVectorEnv(
            [lambda: gymnasium.make(gym_id, max_episode_steps=episode_length) for _ in range(n)]
        )
        envs.reset(seed=0)
    t0 = time.perf_counter()
    for a in actions:
        envs.step(a)
    took = time.perf_counter() - t0
    envs.close()
    return actions.shape[0] * n / took


def _pool(env: VecEnv, actions: np.ndarray) -> float:
    pool = env.env.pool
    pool.reset(np.arange(env.num_envs))
    t0 = time.perf_counter()
    for t, a in enumerate(actions):
        pool.step(a, np.full(env.num_envs, t))
    return actions.shape[0] * env.num_envs / (time.perf_counter() - t0)


def _vec(env: VecEnv, steps: int) -> float:
    def rollout(key):
        state = env.reset(key)
        acts = jax.random.uniform(key, (steps, env.num_envs, env.action_size), minval=-1, maxval=1)
        state, out = jax.lax.scan(lambda s, a: env.step(s, a), state, acts)
        return jnp.sum(out.reward)

    run = jax.jit(rollout)
    jax.block_until_ready(run(jax.random.PRNGKey(0)))  # compile
    t0 = time.perf_counter()
    jax.block_until_ready(run(jax.random.PRNGKey(1)))
    return steps * env.num_envs / (time.perf_counter() - t0)


def _train(name: str, n: int, iterations: int) -> float:
    """Training env steps/s of ``python -m coherent_jax.train`` (its summary), in a process of its own."""
    steps = make_config({"env": name, "num_envs": n}).steps_per_iteration * iterations
    with tempfile.TemporaryDirectory() as tmp:
        args = [f"env={name}", f"num_envs={n}", f"total_steps={steps}", f"run_dir={tmp}/run"]
        subprocess.run([sys.executable, "-m", "coherent_jax.train", *args, "progress=false"], check=True)
        summary = json.loads(Path(f"{tmp}/run/summary.json").read_text())
    return float(summary["train_env_steps_per_s"])


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict[str, Any]:
    """The four rows of each env (module docstring); writes the JSON and returns the result."""
    settings = parse(items).settings
    n, steps = settings["num_envs"], settings["steps"]
    rows = []
    for name in settings["envs"]:
        env = VecEnv(name, n)
        gym_id = name.split(":")[-1]
        rng = np.random.default_rng(0)
        low, high = env.env.source.low, env.env.source.high
        actions = rng.uniform(low, high, (steps, n, env.action_size)).astype(np.float32)
        rates = {
            "sync": _sync(gym_id, n, actions, env.episode_length),
            "pool": _pool(env, actions),
            "vec": _vec(VecEnv(name, n), steps),
            "train": _train(name, n, settings["iterations"]),
        }
        for kind, rate in rates.items():
            rows.append({"env": name, "kind": kind, "env_steps_per_s": rate, "ratio": rate / rates["sync"]})
            log(f"  {name:<20} {kind:<6} {rate:>10,.0f} env steps/s  ({rate / rates['sync']:.2f} x sync)")
    result = {
        "suite": "gym",
        "settings": settings,
        "rows": rows,
        "load_average": os.getloadavg(),
        "machine": {"cpu_count": os.cpu_count(), "jax": jax.__version__, "gymnasium": gymnasium.__version__},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    measure.write_json_atomic(Path(settings["out"]), result)
    log(f"wrote {settings['out']}")
    return result


def format_table(result: dict[str, Any]) -> str:
    """Per env: each row's env steps/s and its ratio to Gymnasium's SyncVectorEnv."""
    load = ", ".join(f"{x:.1f}" for x in result["load_average"])
    lines = [
        f"Gymnasium envs on the host, {result['settings']['num_envs']} envs, "
        f"{result['machine']['cpu_count']} CPUs (load average at the end {load})",
        f"  {'env':<22}{'row':<8}{'env steps/s':>13}{'x sync':>8}",
    ]
    for r in result["rows"]:
        lines.append(f"  {r['env']:<22}{r['kind']:<8}{r['env_steps_per_s']:>13,.0f}{r['ratio']:>8.2f}")
    return "\n".join(lines)
