"""The ``physics`` suite: MJX settings against native MuJoCo on CPU, in one run.

    python -m benchmarks physics [env=halfcheetah] [envs=[16,64,256]] [steps=...]
        [variants=[...]] [repeats=3] [out=bench_results/physics.json]

Every measurement steps `VecEnv` (the code path training uses: physics, time limit,
auto-reset) with uniform random actions inside one jitted ``lax.scan`` of ``steps``
env steps, and reports the median of ``repeats`` timed calls after a warm-up call,
as env steps/s (one env step = the task's ``n_frames`` physics steps). Compile
time is reported apart. Each (variant, env count) runs in its own subprocess, one
after the other, because XLA flags and the host device count are fixed when JAX
starts; all rows come from the same invocation on the same machine.

Variants (`VARIANTS`):

* ``mjx_ls50``: MJX with the solver's line search at Brax's default of 50 iterations;
* ``mjx``: MJX with the registry's settings (``TaskSpec.ls_iterations``), today's MJX path;
* ``mjx_eigen1``: as ``mjx`` with ``--xla_cpu_multi_thread_eigen=false``;
* ``mjx_2dev``: as ``mjx`` with the envs split over two host devices
  (``--xla_force_host_platform_device_count=2``, ``jax.pmap``), to use the second core;
* ``native``: native MuJoCo through ``jax.pure_callback`` (``physics=native``, with its
  default `DEFAULT_THREADS` MuJoCo threads); ``native_all``: the same on every core;
* ``native_raw``: ``mujoco.batch.Batch`` with the default thread count stepped from a
  Python loop with no JAX at all, the ceiling the callback path can approach;
* ``envpool``: EnvPool (C++ threads, ``pip install -e .[bench]``) stepping the same
  Gymnasium task with `DEFAULT_THREADS` threads from a Python loop; ``envpool_all``: on
  every core. Only for Gymnasium's tasks.

The ``standard`` suite (`benchmarks.standard`) times Gymnasium's tasks against
their Brax re-creations and EnvPool with this module's side-by-side worker.

A bad key or value is one line on stderr and exit status 2, before anything runs.
The JSON is written atomically once every row is measured.
"""

from __future__ import annotations

import datetime
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import batch

from benchmarks import measure
from coherent_jax.config import ConfigError, cli
from coherent_jax.envs.physics import mujoco_model
from coherent_jax.envs.registry import DEFAULT_THREADS, NATIVE_TASKS, check_task
from coherent_jax.envs.vec_env import VecEnv

VARIANTS: dict[str, dict[str, Any]] = {
    "mjx_ls50": {"physics": "mjx", "ls_iterations": 50},
    "mjx": {"physics": "mjx"},
    "mjx_eigen1": {"physics": "mjx", "xla_flags": "--xla_cpu_multi_thread_eigen=false"},
    "mjx_2dev": {"physics": "mjx", "devices": 2, "xla_flags": "--xla_force_host_platform_device_count=2"},
    "native": {"physics": "native"},
    "native_all": {"physics": "native", "nthread": 0},
    "native_raw": {"physics": "raw"},
    "envpool": {"physics": "envpool"},
    "envpool_all": {"physics": "envpool", "nthread": 0},
}
# Rough env steps/s used only to size a timed call when steps=0.
_GUESS = {"mjx": 3000, "native": 30000, "raw": 30000, "envpool": 20000, "generalized": 3000}


# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~1 h (stopped at 1,800 s after 12 of 27 rows; MJX rows 188-393 s, native 15-38 s)"
KEYS: dict[str, cli.Key] = {
    "env": cli.Key("halfcheetah", cli.choice(tuple(NATIVE_TASKS)), ", ".join(NATIVE_TASKS), "the task"),
    "envs": cli.Key([16, 64, 256], cli.int_list(1), "a list of integers >= 1, e.g. [16,64]", "env counts"),
    "steps": cli.Key(
        0,
        cli.int_at_least(0),
        "an integer >= 0",
        "env steps per timed call; 0: chosen per row so that a call takes about a second",
    ),
    "variants": cli.Key(list(VARIANTS), cli.choice_list(tuple(VARIANTS)), ", ".join(VARIANTS), "rows"),
    "repeats": cli.Key(3, cli.int_at_least(1), "an integer >= 1", "timed calls per row (median)"),
    "out": cli.Key(
        "bench_results/physics.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings (no training config); `ConfigError` in one line for bad input."""
    parsed = cli.parse_command(items, KEYS, command="the physics suite", config=False)
    settings = parsed.settings
    if "mjx_2dev" in settings["variants"] and any(n % 2 for n in settings["envs"]):
        raise ConfigError(
            f"invalid value for 'envs': {settings['envs']} (allowed: even counts with variant mjx_2dev)"
        )
    return parsed


# ------------------------------------------------------------------ one measurement (subprocess)
def _timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _measure_raw(task: str, n: int, steps: int, repeats: int) -> dict[str, Any]:
    """``mujoco.batch.Batch`` from a Python loop: load rows, set controls, step, read back."""
    model, n_frames, _, init_q = mujoco_model(task)
    b = batch.Batch(model, n, nthread=min(DEFAULT_THREADS or os.cpu_count() or 1, n))
    xpos, ctrl = b.bind("xpos"), b.bind("ctrl")
    b.reset()
    b.bind("qpos")[:] = init_q
    rows = b.state.copy()
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, (steps, n, model.nu))

    def run():
        nonlocal rows
        for t in range(steps):
            b.state[:] = rows
            ctrl[:] = actions[t]
            b.step(nstep=n_frames)
            rows = b.state.copy()
            _ = xpos[:, 1].copy()

    run()
    return {"compile_s": 0.0, "call_s": _timed(run, repeats)}


def _measure_envpool(task: str, n: int, steps: int, repeats: int, nthread: int) -> dict[str, Any]:
    call, threads = _prepare_envpool(task, n, steps, nthread)
    return {"compile_s": 0.0, "call_s": _timed(call, repeats), "physics": "envpool", "threads": threads}


def _prepare_envpool(task: str, n: int, steps: int, nthread: int):
    """EnvPool's own vectorized env of the same Gymnasium task: a warm call of `steps` random-action
    steps of all `n` envs, and the thread count."""
    import envpool  # lazy: optional, pip ".[bench]"

    gym_id = check_task(task).gymnasium_id
    if not gym_id:
        raise ValueError(f"EnvPool runs Gymnasium's tasks only, not {task!r}")
    threads = min(nthread or os.cpu_count() or 1, n)
    env = envpool.make_gymnasium(gym_id, num_envs=n, batch_size=n, num_threads=threads, seed=0)
    env.reset()
    low, high = env.action_space.low, env.action_space.high
    actions = np.random.default_rng(0).uniform(low, high, (steps, n, len(low)))

    def run():
        for t in range(steps):
            env.step(actions[t])

    run()
    return run, threads


def _measure_jax(task: str, n: int, steps: int, repeats: int, variant: dict[str, Any]) -> dict[str, Any]:
    call, compile_s, physics = _prepare_jax(task, n, steps, variant)
    return {"compile_s": compile_s, "call_s": _timed(call, repeats), "physics": physics}


def set_ls_iterations(env, iterations: int) -> None:
    """Sets the MJX solver's line-search iterations of `env` (a `VecEnv` on MJX) before it is traced.

    Brax's environments keep their MJX model as ``sys``, Gymnasium's tasks on MJX
    (`coherent_jax.envs.physics.MjxPhysics`) as ``model``.
    """
    name = "sys" if hasattr(env.env, "sys") else "model"
    setattr(env.env, name, getattr(env.env, name).tree_replace({"opt.ls_iterations": iterations}))


def _prepare_jax(task: str, n: int, steps: int, variant: dict[str, Any]):
    """A warm call of `steps` jitted VecEnv steps of `n` envs, its compile seconds and the physics."""
    devices = int(variant.get("devices", 1))
    env = VecEnv(task, n // devices, physics=variant["physics"])
    if "ls_iterations" in variant:
        set_ls_iterations(env, int(variant["ls_iterations"]))
    if "nthread" in variant:
        env.env.host.nthread = int(variant["nthread"]) or os.cpu_count() or 1

    def run(state, key):
        def body(s, k):
            action = jax.random.uniform(k, (env.num_envs, env.action_size), minval=-1.0, maxval=1.0)
            s, out = env.step(s, action)
            return s, out.reward.sum()

        state, rewards = jax.lax.scan(body, state, jax.random.split(key, steps))
        return state, rewards.sum()

    keys = jax.random.split(jax.random.PRNGKey(0), devices)
    if devices > 1:
        if jax.device_count() < devices:
            raise RuntimeError(f"{devices} devices requested, {jax.device_count()} available")
        fn = jax.pmap(run)
        state = jax.pmap(env.reset)(keys)
        step_keys = keys
        t0 = time.perf_counter()
        jax.block_until_ready(fn(state, step_keys))  # pmap compiles on first call
        compile_s = time.perf_counter() - t0
    else:
        state = jax.jit(env.reset)(keys[0])
        step_keys = keys[0]
        t0 = time.perf_counter()
        fn = jax.jit(run).lower(state, step_keys).compile()
        compile_s = time.perf_counter() - t0
        jax.block_until_ready(fn(state, step_keys))  # warm-up

    holder = {"state": state}

    def call():
        holder["state"], total = fn(holder["state"], step_keys)
        jax.block_until_ready(total)
        if not bool(jnp.all(jnp.isfinite(total))):
            raise FloatingPointError("non-finite reward")

    return call, compile_s, env.physics


def _side_by_side(spec: dict[str, Any]) -> dict[str, Any]:
    """Several (kind, env, variant) rows in one process, timed round-robin so that they share the load."""
    calls, rows = {}, {}
    for kind, env, name in spec["plan"]:
        variant = VARIANTS[name]
        try:
            if variant["physics"] == "envpool":
                calls[kind], threads = _prepare_envpool(
                    env, spec["n"], spec["steps"], variant.get("nthread", DEFAULT_THREADS)
                )
                rows[kind] = {"compile_s": 0.0, "physics": "envpool", "threads": threads}
            else:
                calls[kind], compile_s, physics = _prepare_jax(env, spec["n"], spec["steps"], variant)
                rows[kind] = {"compile_s": compile_s, "physics": physics}
        except Exception as exc:  # a row that cannot run (e.g. EnvPool not installed) is reported, not fatal
            rows[kind] = {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
        rows[kind].update({"kind": kind, "env": env, "variant": name})
    # Wall time, and the process's CPU time (every thread): on a loaded machine the scheduler
    # shares CPU unevenly between a thread pool that sleeps between calls and one that spins.
    times: dict[str, list[tuple[float, float]]] = {kind: [] for kind in calls}
    for _ in range(spec["repeats"]):
        for kind, call in calls.items():
            t0, c0 = time.perf_counter(), time.process_time()
            call()
            times[kind].append((time.perf_counter() - t0, time.process_time() - c0))
    for kind, ts in times.items():
        rows[kind]["call_s"] = statistics.median(t for t, _ in ts)
        rows[kind]["cpu_s"] = statistics.median(c for _, c in ts)
        rows[kind]["env_steps_per_s"] = spec["n"] * spec["steps"] / rows[kind]["call_s"]
        rows[kind]["env_steps_per_cpu_s"] = spec["n"] * spec["steps"] / max(rows[kind]["cpu_s"], 1e-9)
    return {**spec, "rows": list(rows.values()), "load_average": os.getloadavg()}


def _worker(spec: dict[str, Any]) -> dict[str, Any]:
    if "plan" in spec:
        return _side_by_side(spec)
    variant = VARIANTS[spec["variant"]]
    if variant["physics"] == "raw":
        out = _measure_raw(spec["env"], spec["n"], spec["steps"], spec["repeats"])
    elif variant["physics"] == "envpool":
        nthread = variant.get("nthread", DEFAULT_THREADS)
        out = _measure_envpool(spec["env"], spec["n"], spec["steps"], spec["repeats"], nthread)
    else:
        out = _measure_jax(spec["env"], spec["n"], spec["steps"], spec["repeats"], variant)
    out["env_steps_per_s"] = spec["n"] * spec["steps"] / out["call_s"]
    return {**spec, **out}


def _run_row(settings: dict[str, Any], name: str, n: int) -> dict[str, Any]:
    variant = VARIANTS[name]
    steps = settings["steps"] or max(10, int(_GUESS[variant["physics"]] / n))
    spec = {"variant": name, "env": settings["env"], "n": n, "steps": steps, "repeats": settings["repeats"]}
    return _spawn(spec, variant.get("xla_flags"))


def _spawn(spec: dict[str, Any], flags: str | None = None) -> dict[str, Any]:
    """Runs one worker `spec` in a fresh process (XLA flags are fixed when JAX starts)."""
    env = dict(os.environ)
    if flags:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flags).strip()
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.physics", "--worker", json.dumps(spec)],
        env=env,
        capture_output=True,
        text=True,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {**spec, "error": tail}
    return json.loads(lines[-1])


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict[str, Any]:
    """Measures every (variant, env count) row, logging each as it is done; writes and returns
    the results. Raises `ConfigError` for bad input before anything runs."""
    settings = parse(items).settings
    rows = []
    total = len(settings["variants"]) * len(settings["envs"])
    log(f"physics bench: {settings['env']}, {total} measurements, one subprocess each")
    for n in settings["envs"]:
        for name in settings["variants"]:
            t0 = time.perf_counter()
            row = _run_row(settings, name, n)
            rows.append(row)
            status = row.get("error") or f"{row['env_steps_per_s']:,.0f} env steps/s"
            took = time.perf_counter() - t0
            log(f"  [{len(rows)}/{total}] {name:<11} {n:>5} envs: {status} ({took:.0f} s)")
    for row in rows:
        base = next(
            (r for r in rows if r["variant"] == "mjx" and r["n"] == row["n"] and "error" not in r), None
        )
        if base and "error" not in row:
            row["speedup_vs_mjx"] = row["env_steps_per_s"] / base["env_steps_per_s"]
    result = {
        "suite": "physics",
        "env": settings["env"],
        "settings": settings,
        "rows": rows,
        "machine": {"cpu_count": os.cpu_count(), "jax": jax.__version__, "mujoco": mujoco.__version__},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    measure.write_json_atomic(Path(settings["out"]), result)
    log(f"wrote {settings['out']}")
    return result


def format_table(result: dict[str, Any]) -> str:
    """The human-readable summary of `run`'s result."""
    lines = [
        f"physics bench: {result['env']} on {result['machine']['cpu_count']} CPUs, "
        f"jax {result['machine']['jax']}, mujoco {result['machine']['mujoco']}",
        f"  {'variant':<12}{'envs':>6}{'compile s':>11}{'env steps/s':>14}{'vs mjx':>9}",
    ]
    for row in result["rows"]:
        if "error" in row:
            lines.append(f"  {row['variant']:<12}{row['n']:>6}  failed: {row['error']}")
            continue
        speedup = row.get("speedup_vs_mjx")
        lines.append(
            f"  {row['variant']:<12}{row['n']:>6}{row['compile_s']:>11.1f}{row['env_steps_per_s']:>14,.0f}"
            + (f"{speedup:>8.1f}x" if speedup else f"{'-':>9}")
        )
    return "\n".join(lines)


if __name__ == "__main__":  # one measurement in a fresh process: ``--worker SPEC_JSON``
    if sys.argv[1:2] != ["--worker"] or len(sys.argv) != 3:
        sys.exit("usage: python -m benchmarks.physics --worker SPEC_JSON (run by the physics suite)")
    print(json.dumps(_worker(json.loads(sys.argv[2]))), flush=True)
