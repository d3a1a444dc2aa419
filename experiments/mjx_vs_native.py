"""How close Gymnasium's tasks on MJX (``physics=mjx``) stay to native MuJoCo (= Gymnasium).

    python experiments/mjx_vs_native.py [--steps 1000] [--tasks Hopper-v5 Ant-v5] [--out FILE]

For every task MJX can run: from the same initial states (same keys) and the same
uniform random actions (2 envs), the longest prefix of steps over which MJX's
observations agree with native MuJoCo's to 1e-3 relative (|d| / (1 + |obs|)), rewards
to 1e-3 (relative or absolute) and terminations exactly; then the largest relative
observation error over the first 10 and the first 100 steps. Native MuJoCo equals
Gymnasium step for step (``tests/test_gymnasium_tasks.py``), so this is MJX against
Gymnasium. Also MJX's compile time and the env steps/s of a jitted scan of each
engine on this machine (64 envs, random actions: MJX is the path for accelerators;
on a CPU native MuJoCo is the fast one). Writes JSON (default
``bench_results/mjx_vs_native.json``) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coherent_jax.envs import VecEnv  # noqa: E402
from coherent_jax.envs.gym_v5 import GYM_TASKS  # noqa: E402
from coherent_jax.envs.registry import MJX_REFUSAL  # noqa: E402

TOL = 1e-3


def _rollout(env, keys, actions):
    t0 = time.perf_counter()
    compiled = jax.jit(env.trajectory).lower(keys, actions).compile()
    compile_s = time.perf_counter() - t0
    return jax.device_get(compiled(keys, actions)), compile_s


def _rate(env, num_envs: int, steps: int) -> float:
    """Env steps/s of a jitted scan of `steps` random-action steps (after one warm-up call)."""
    keys = jax.random.split(jax.random.PRNGKey(5), num_envs)
    actions = jax.random.uniform(
        jax.random.PRNGKey(6), (steps, num_envs, env.action_size), minval=-1, maxval=1
    )

    @jax.jit
    def go(keys, actions):
        return jax.lax.scan(lambda s, a: (env.step(s, a), None), env.reset(keys), actions)[0].obs

    jax.block_until_ready(go(keys, actions))
    t0 = time.perf_counter()
    jax.block_until_ready(go(keys, actions))
    return num_envs * steps / (time.perf_counter() - t0)


def compare(gym_id: str, steps: int) -> dict:
    n = 2
    mjx_env, native_env = VecEnv(gym_id, n, physics="mjx").env, VecEnv(gym_id, n, physics="native").env
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    actions = jax.random.uniform(
        jax.random.PRNGKey(1), (steps, n, native_env.action_size), minval=-1, maxval=1
    )
    (obs0_m, (obs_m, rew_m, done_m)), compile_s = _rollout(mjx_env, keys, actions)
    (obs0_n, (obs_n, rew_n, done_n)), _ = _rollout(native_env, keys, actions)
    obs_err = np.max(np.abs(obs_m - obs_n) / (1.0 + np.abs(obs_n)), axis=(1, 2))
    rew_err = np.max(np.abs(rew_m - rew_n) / np.maximum(1.0, np.abs(rew_n)), axis=1)
    ok = (obs_err < TOL) & (rew_err < TOL) & np.all(done_m == done_n, axis=1)
    matching = int(np.argmin(ok)) if not ok.all() else steps
    return {
        "task": gym_id,
        "steps_compared": steps,
        "matching_steps": matching,
        "initial_obs_max_abs_diff": float(np.max(np.abs(obs0_m - obs0_n))),
        "max_rel_obs_err_10": float(obs_err[:10].max()),
        "max_rel_obs_err_100": float(obs_err[:100].max()),
        "mjx_compile_s": compile_s,
        "mjx_env_steps_per_s": _rate(VecEnv(gym_id, 64, physics="mjx").env, 64, 100),
        "native_env_steps_per_s": _rate(VecEnv(gym_id, 64, physics="native").env, 64, 100),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    mjx_tasks = [g for g in GYM_TASKS if g not in MJX_REFUSAL]
    parser.add_argument("--tasks", nargs="*", default=mjx_tasks, choices=mjx_tasks, metavar="TASK")
    parser.add_argument("--out", default=str(ROOT / "bench_results" / "mjx_vs_native.json"))
    args = parser.parse_args(argv)
    rows = []
    for gym_id in args.tasks:
        row = compare(gym_id, args.steps)
        print(json.dumps(row), flush=True)
        rows.append(row)
    result = {"jax": jax.__version__, "tolerance": TOL, "refused": dict(MJX_REFUSAL), "tasks": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    os.replace(tmp, out)
    print(
        "| task | matching steps | max rel. obs error, 10 / 100 steps | MJX compile "
        "| env steps/s MJX / native (CPU) |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['task']} | {r['matching_steps']} of {r['steps_compared']} | "
            f"{r['max_rel_obs_err_10']:.1e} / {r['max_rel_obs_err_100']:.1e} | {r['mjx_compile_s']:.0f} s | "
            f"{r['mjx_env_steps_per_s']:,.0f} / {r['native_env_steps_per_s']:,.0f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
