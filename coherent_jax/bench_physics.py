"""Physics throughput on CPU: MJX settings against native MuJoCo, in one run.

    python -m coherent_jax.bench_physics [env=halfcheetah] [envs=[16,64,256]] [steps=...]
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

``python -m coherent_jax.bench_physics standard [tasks=[...]] [envs=[64]] [steps=...]
[repeats=3] [out=bench_results/physics_standard.json]`` measures, for each standard task
at 1 thread and at every core, our vectorized env of the Gymnasium task (native), its
Brax re-creation (``brax-*``, on the physics ``auto`` picks) and EnvPool, the same envs
and threads, as rows of the same kind (`standard_tasks`).

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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

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
DEFAULTS: dict[str, Any] = {
    "env": "halfcheetah",
    "envs": [16, 64, 256],
    "steps": 0,  # 0: chosen per row so that one timed call takes about a second
    "variants": list(VARIANTS),
    "repeats": 3,
    "out": "bench_results/physics.json",
}
# Rough env steps/s used only to size a timed call when steps=0.
_GUESS = {"mjx": 3000, "native": 30000, "raw": 30000, "envpool": 20000, "generalized": 3000}


class BenchError(ValueError):
    """A bad key=value setting."""


def _int_list(key: str, text: str) -> list[int]:
    items = [s.strip() for s in text.strip().strip("[]").split(",") if s.strip()]
    try:
        values = [int(s) for s in items]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise BenchError(
            f"invalid value for {key!r}: {text!r} (allowed: a list of integers >= 1, e.g. [16,64])"
        )
    return values


def parse_settings(argv: Sequence[str]) -> dict[str, Any]:
    """``key=value`` strings to settings; raises `BenchError` naming the bad key or value."""
    from coherent_jax.envs.native import NATIVE_TASKS

    settings = dict(DEFAULTS)
    for item in argv:
        if "=" not in item or item.startswith("="):
            raise BenchError(f"malformed setting {item!r}: expected key=value")
        key, text = (s.strip() for s in item.split("=", 1))
        if key not in DEFAULTS:
            raise BenchError(f"unknown key {key!r}; valid keys: {', '.join(DEFAULTS)}")
        if key == "env":
            if text not in NATIVE_TASKS:
                raise BenchError(f"invalid value for 'env': {text!r} (allowed: {', '.join(NATIVE_TASKS)})")
            settings[key] = text
        elif key == "envs":
            settings[key] = _int_list(key, text)
        elif key == "variants":
            names = [s.strip() for s in text.strip().strip("[]").split(",") if s.strip()]
            if not names or any(n not in VARIANTS for n in names):
                raise BenchError(f"invalid value for 'variants': {text!r} (allowed: {', '.join(VARIANTS)})")
            settings[key] = names
        elif key in ("steps", "repeats"):
            low = 0 if key == "steps" else 1
            if not text.isdigit() or int(text) < low:
                raise BenchError(f"invalid value for {key!r}: {text!r} (allowed: an integer >= {low})")
            settings[key] = int(text)
        else:  # out
            if not text or Path(text).is_dir():
                raise BenchError(f"invalid value for 'out': {text!r} (allowed: a file path)")
            settings[key] = text
    if "mjx_2dev" in settings["variants"] and any(n % 2 for n in settings["envs"]):
        raise BenchError(
            f"invalid value for 'envs': {settings['envs']} (allowed: even counts with variant mjx_2dev)"
        )
    return settings


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
    import numpy as np
    from mujoco import batch

    from coherent_jax.envs.native import DEFAULT_THREADS, mujoco_model

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
    import envpool
    import numpy as np

    from coherent_jax.envs.registry import check_task

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


def _prepare_jax(task: str, n: int, steps: int, variant: dict[str, Any]):
    """A warm call of `steps` jitted VecEnv steps of `n` envs, its compile seconds and the physics."""
    import jax
    import jax.numpy as jnp

    from coherent_jax.envs.vec_env import VecEnv

    devices = int(variant.get("devices", 1))
    env = VecEnv(task, n // devices, physics=variant["physics"])
    if "ls_iterations" in variant:
        env.env.sys = env.env.sys.tree_replace({"opt.ls_iterations": variant["ls_iterations"]})
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
    from coherent_jax.envs.native import DEFAULT_THREADS

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
        from coherent_jax.envs.native import DEFAULT_THREADS

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
        [sys.executable, "-m", "coherent_jax.bench_physics", "--worker", json.dumps(spec)],
        env=env,
        capture_output=True,
        text=True,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {**spec, "error": tail}
    return json.loads(lines[-1])


def run(settings: dict[str, Any]) -> dict[str, Any]:
    """Measures every (variant, env count) row; prints each as it is done."""
    import jax
    import mujoco

    rows = []
    total = len(settings["variants"]) * len(settings["envs"])
    print(f"physics bench: {settings['env']}, {total} measurements, one subprocess each", flush=True)
    for n in settings["envs"]:
        for name in settings["variants"]:
            t0 = time.perf_counter()
            row = _run_row(settings, name, n)
            rows.append(row)
            status = row.get("error") or f"{row['env_steps_per_s']:,.0f} env steps/s"
            took = time.perf_counter() - t0
            print(
                f"  [{len(rows)}/{total}] {name:<11} {n:>5} envs: {status} ({took:.0f} s)",
                flush=True,
            )
    for row in rows:
        base = next(
            (r for r in rows if r["variant"] == "mjx" and r["n"] == row["n"] and "error" not in r), None
        )
        if base and "error" not in row:
            row["speedup_vs_mjx"] = row["env_steps_per_s"] / base["env_steps_per_s"]
    return {
        "suite": "physics",
        "env": settings["env"],
        "settings": settings,
        "rows": rows,
        "machine": {"cpu_count": os.cpu_count(), "jax": jax.__version__, "mujoco": mujoco.__version__},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def format_table(result: dict[str, Any]) -> str:
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


# ------------------------------------------------------------------ standard tasks vs Brax vs EnvPool
STANDARD_DEFAULTS: dict[str, Any] = {
    "tasks": ["halfcheetah", "hopper", "walker2d", "ant", "humanoid"],
    "envs": [64],
    "steps": 0,
    "repeats": 3,
    "out": "bench_results/physics_standard.json",
}


def parse_standard(argv: Sequence[str]) -> dict[str, Any]:
    """``key=value`` settings of the ``standard`` suite; raises `BenchError` naming the bad key or value."""
    from coherent_jax.envs.gym_v5 import SHORT_NAMES

    settings = dict(STANDARD_DEFAULTS)
    for item in argv:
        if "=" not in item or item.startswith("="):
            raise BenchError(f"malformed setting {item!r}: expected key=value")
        key, text = (s.strip() for s in item.split("=", 1))
        if key not in STANDARD_DEFAULTS:
            raise BenchError(f"unknown key {key!r}; valid keys: {', '.join(STANDARD_DEFAULTS)}")
        if key == "tasks":
            names = [s.strip() for s in text.strip().strip("[]").split(",") if s.strip()]
            if not names or any(n not in SHORT_NAMES for n in names):
                raise BenchError(f"invalid value for 'tasks': {text!r} (allowed: {', '.join(SHORT_NAMES)})")
            settings[key] = names
        elif key == "envs":
            settings[key] = _int_list(key, text)
        elif key in ("steps", "repeats"):
            low = 0 if key == "steps" else 1
            if not text.isdigit() or int(text) < low:
                raise BenchError(f"invalid value for {key!r}: {text!r} (allowed: an integer >= {low})")
            settings[key] = int(text)
        else:  # out
            if not text or Path(text).is_dir():
                raise BenchError(f"invalid value for 'out': {text!r} (allowed: a file path)")
            settings[key] = text
    return settings


def standard_tasks(settings: dict[str, Any]) -> dict[str, Any]:
    """Env steps/s of each standard task (Gymnasium's, native), its Brax re-creation and EnvPool.

    One process per task, env count and thread count (1, then every core), timing the
    three round-robin so that they share the machine's load: our ``VecEnv`` of the
    Gymnasium task (``native``/``native_all``), EnvPool on the same task with the same
    threads (``envpool``/``envpool_all``), and the Brax re-creation (``brax-*``) on the
    physics ``physics=auto`` picks for it here (native MuJoCo for six of Brax's tasks,
    with the same threads; else MJX, whose threads XLA chooses, measured at 1 only).
    """
    import jax
    import mujoco

    from coherent_jax.envs.native import resolve_physics

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
                result = _spawn(spec)
                took = time.perf_counter() - t0
                if "error" in result:
                    result["rows"] = [{"kind": kind, "error": result["error"]} for kind, _, _ in plan]
                for row in result["rows"]:
                    rows.append({**row, "task": task, "n": n, "threads": threads})
                    status = row.get("error") or f"{row['env_steps_per_s']:,.0f} env steps/s"
                    print(f"  {task:<12} {row['kind']:<8} {n:>5} envs, threads {threads or 'all'}: {status}")
                print(f"  ({took:.0f} s, load average {result.get('load_average')})", flush=True)
    return {
        "suite": "physics_standard",
        "settings": settings,
        "rows": rows,
        "load_average": os.getloadavg(),
        "machine": {"cpu_count": os.cpu_count(), "jax": jax.__version__, "mujoco": mujoco.__version__},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def format_standard(result: dict[str, Any]) -> str:
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


def _write(result: dict[str, Any], path: str) -> None:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, out)
    print(f"wrote {out}")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--worker"]:
        print(json.dumps(_worker(json.loads(argv[1]))), flush=True)
        return 0
    if argv[:1] == ["standard"]:
        try:
            settings = parse_standard(argv[1:])
        except BenchError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        result = standard_tasks(settings)
        print(format_standard(result))
        _write(result, settings["out"])
        return 0
    try:
        settings = parse_settings(argv)
    except BenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = run(settings)
    print(format_table(result))
    out = Path(settings["out"])
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
