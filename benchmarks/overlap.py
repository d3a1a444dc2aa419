"""The ``overlap`` suite: ``python -m benchmarks overlap [key=value ...]``, a probe.

Can the host physics (native MuJoCo through a ``jax.pure_callback``,
`coherent_jax.envs.physics.NativePhysics`) run while the program computes the policy,
if the envs are stepped as K groups inside the scanned step? Two ways
(`benchmarks.overlap_groups`):

* ``gK`` (**groups**): K independent chains per step, left to XLA's CPU runtime to
  run at once (``g1`` is the package's own `coherent_jax.agents.rollout.unroll`);
* ``pK`` (**pipeline**, K >= 2): the K groups in a ring whose physics runs on a host
  worker thread between a ``start`` and a ``finish`` callback.

For each way and K, three programs ``(state) -> (state, figures)``, compiled and called
once, then timed interleaved (the order flips every round):

* ``raw/..``: the vectorized env alone with random actions;
* ``rollout/..``: the PPO iteration's rollout (``unroll_length`` steps of the policy on
  normalised observations, at the trainer's initial parameters);
* ``iteration/..``: the whole PPO iteration (rollout, GAE, updates), traced with the
  way's rollout in place of the package's `unroll` (`_iteration_with`).

Besides the wall time of each call, the seconds spent inside MuJoCo's host step
(`overlap_groups.HostClock`): what the physics costs, and so what an overlap could hide
at most (``ideal_s``: the host's seconds or the rest, whichever is longer, plus, for the
iteration, the update that follows the rollout). ``runtime``: whether XLA's CPU runtime
runs two independent host callbacks at once (two 20 ms sleeps in one program; sleeping
needs no CPU, so the figure does not depend on the machine's load), and whether they
overlap when one runs on the ring's worker thread. Results go to a
JSON file (default ``bench_results/overlap.json``), written atomically; the load
average is recorded at the start, after each round and at the end.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import IGNORED, measure
from benchmarks.overlap_groups import HostClock, TwoPhaseHost, grouped_unroll, pipelined_unroll, timed_env
from coherent_jax.agents import make_trainer, onpolicy
from coherent_jax.agents.rollout import unroll
from coherent_jax.config import Config, ConfigError, cli, to_dict
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.exploration.base import ActOutput
from coherent_jax.networks import normalize

# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~11 min (646 s measured; 12 programs compiled, each ~25-65 s)"
KEYS: dict[str, cli.Key] = {
    "groups": cli.Key(
        [1, 2, 4],
        cli.int_list(1),
        "a list of distinct integers >= 1 that divide num_envs",
        "independent env groups per scanned step (1 = the package's rollout)",
    ),
    "pipeline": cli.Key(
        [2],
        cli.int_list(0),
        "a list of distinct integers >= 2 that divide num_envs, or [0] for none",
        "env groups in a ring with their physics on a host worker thread",
    ),
    "rounds": cli.Key(7, cli.int_at_least(1), "an integer >= 1", "timed calls of each program"),
    "out": cli.Key(
        "bench_results/overlap.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
}
# PPO's policy and value, on native MuJoCo: the callback whose time the probe would hide.
FIXED: dict[str, str | None] = {"algo": "ppo", "physics": "native"}
PROGRAMS = ("raw", "rollout", "iteration")
SLEEP_S = 0.02  # each callback of the runtime check


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and PPO config; `ConfigError` in one line for bad input."""
    parsed = cli.parse_command(items, KEYS, command="the overlap suite", fixed=FIXED, ignored=IGNORED)
    n = parsed.config.num_envs
    for key, low in (("groups", 1), ("pipeline", 2)):
        values = parsed.settings[key]
        if key == "pipeline" and values == [0]:
            parsed.settings[key] = []
            continue
        if len(set(values)) != len(values) or any(k < low or n % k for k in values):
            raise ConfigError(
                f"invalid value for {key!r}: {values} (allowed: {KEYS[key].allowed}; num_envs={n})"
            )
    return parsed


# --------------------------------------------------------------------------- the programs
class Ways:
    """Each way's rollout function ``(env, act, env_state, carry, key, length)`` by name
    (``g1``, ``g2``, ``p2``, ...), its group envs timed by ``clock``."""

    def __init__(self, cfg: Config, clock: HostClock):
        self.cfg, self.clock = cfg, clock

    def _envs(self, k: int) -> list[VecEnv]:
        c = self.cfg
        return [
            timed_env(
                VecEnv(c.env, c.num_envs // k, c.episode_length, c.physics, c.physics_threads), self.clock
            )
            for _ in range(k)
        ]

    def unroll(self, way: str) -> Callable:
        kind, k = way[0], int(way[1:])
        if way == "g1":
            return unroll
        envs = self._envs(k)
        if kind == "g":
            return lambda env, *args: grouped_unroll(envs, *args)
        host = TwoPhaseHost()
        return lambda env, *args: pipelined_unroll(envs, host, *args)


def _raw(cfg: Config, env: VecEnv, unroll_fn: Callable) -> Callable:
    """``((env_state, key)) -> ((env_state, key), figures)``: random actions."""

    def act(key, carry, obs, first):
        action = jax.random.uniform(key, (obs.shape[0], env.action_size), minval=-1.0, maxval=1.0)
        return ActOutput(action, jnp.zeros(obs.shape[:1]), carry)

    def program(state):
        env_state, key = state
        key, sub = jax.random.split(key)
        env_state, _, data = unroll_fn(env, act, env_state, (), sub, cfg.unroll_length)
        return (env_state, key), {"reward_sum": data.reward.sum()}

    return program


def _rollout(cfg: Config, trainer, unroll_fn: Callable) -> Callable:
    """``(TrainState) -> (TrainState, figures)``: the PPO iteration's rollout alone, at fixed parameters."""

    def program(state):
        hp, params, stats = state.hparams, state.params, state.obs_stats

        def act(key, carry, obs, first):
            obs = normalize(stats, obs, cfg.normalize_obs)
            return trainer.strategy.act(key, params.policy, hp.explore, carry, obs, first)

        key, sub = jax.random.split(state.key)
        env_state, carry, data = unroll_fn(
            trainer.env, act, state.env_state, state.carry, sub, cfg.unroll_length
        )
        return state.replace(env_state=env_state, carry=carry, key=key), {"reward_sum": data.reward.sum()}

    return program


def _iteration_with(trainer, unroll_fn: Callable) -> Callable:
    """The trainer's iteration, traced with ``unroll_fn`` in place of the package's `unroll`."""

    def program(state):
        with mock.patch.object(onpolicy, "unroll", unroll_fn):
            return trainer.iteration(state)

    return program


def _programs(cfg: Config, ways: list[str], clock: HostClock, log) -> dict[str, dict]:
    """Every program of the suite, compiled and warm (`measure.warm_iteration`)."""
    env = timed_env(
        VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads), clock
    )
    trainer = make_trainer(cfg, env=env, eval_env=env)  # no evaluation runs here
    key = jax.random.PRNGKey(cfg.seed)
    train_state = jax.jit(trainer.init)(key)
    factory = Ways(cfg, clock)
    runs: dict[str, dict] = {}
    for way in ways:
        shape = f"{way}: {way[1:]} group(s) of {cfg.num_envs // int(way[1:])} envs"
        programs = {
            "raw": (_raw(cfg, env, factory.unroll(way)), (train_state.env_state, key), "the raw env"),
            "rollout": (_rollout(cfg, trainer, factory.unroll(way)), train_state, "the PPO rollout"),
            "iteration": (_iteration_with(trainer, factory.unroll(way)), train_state, "the PPO iteration"),
        }
        for program, (fn, state, what) in programs.items():
            runs[f"{program}/{way}"] = measure.warm_iteration(fn, state, log, f"{what}, {shape}")
            runs[f"{program}/{way}"]["host_s"] = []
    clock.take()
    return runs


def runtime_check(rounds: int) -> dict[str, Any]:
    """Two independent host callbacks that sleep `SLEEP_S` each, in one jitted program: the
    median seconds per pair over ``2 * SLEEP_S`` (1.0: one after the other; 0.5: at once),
    at the top level, inside a 10-step scan, and with one sleep on `TwoPhaseHost`'s worker
    between its ``start`` and ``finish`` while the other runs as a plain callback (the ring's way)."""
    shape = jax.ShapeDtypeStruct((8,), jnp.float32)
    host = TwoPhaseHost()

    def sleep(x, *after):
        time.sleep(SLEEP_S)
        return np.asarray(x)

    def pair(a, b):
        return jax.pure_callback(sleep, shape, a), jax.pure_callback(sleep, shape, b)

    def scanned(a, b):
        return jax.lax.scan(lambda c, _: (pair(*c), None), (a, b), None, length=10)[0]

    def two_phase(a, b):
        ticket = jax.pure_callback(
            lambda x: host.start(sleep, x, x, True), jax.ShapeDtypeStruct((), jnp.int32), b
        )
        a = jax.pure_callback(sleep, shape, a, ticket)
        return a, jax.pure_callback(host.finish, shape, ticket, a)

    out = {}
    x = jnp.zeros((8,))
    for name, fn, pairs in (("top_level", pair, 1), ("in_scan", scanned, 10), ("two_phase", two_phase, 1)):
        f = jax.jit(fn)
        jax.block_until_ready(f(x, x))
        times = []
        for _ in range(rounds):
            t0 = time.perf_counter()
            jax.block_until_ready(f(x, x))
            times.append(time.perf_counter() - t0)
        out[name] = statistics.median(times) / (pairs * 2 * SLEEP_S)
    return out


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results."""
    bench, cfg, _ = parse(items)
    info, t_start = measure.start("overlap", log)
    runtime = runtime_check(bench["rounds"])
    log(f"[bench] two independent {SLEEP_S * 1e3:.0f} ms callbacks take {runtime} x their sum")
    clock = HostClock()
    ways = [f"g{k}" for k in bench["groups"]] + [f"p{k}" for k in bench["pipeline"]]
    runs = _programs(cfg, ways, clock, log)
    names = list(runs)
    loads = []
    for i in range(bench["rounds"]):
        for name in names if i % 2 == 0 else names[::-1]:  # the order flips every round
            r = runs[name]
            t0 = time.perf_counter()
            r["state"], _ = jax.block_until_ready(r["step"](r["state"]))
            r["times"].append(time.perf_counter() - t0)
            r["host_s"].append(clock.take())
        loads.append(measure.load_average())
        log(
            f"[bench] round {i + 1}/{bench['rounds']}: "
            + ", ".join(f"{n} {runs[n]['times'][-1]:.3f} s" for n in names)
            + f"; load {loads[-1]}"
        )
    rows = _rows(runs, cfg.steps_per_iteration)
    figures = {
        "env_steps_per_iteration": cfg.steps_per_iteration,
        "runtime_pair_over_sum": runtime,
        "rows": rows,
        "ratios": _ratios(rows, ways),
        "load_average_rounds": loads,
    }
    settings = {"config": to_dict(cfg), **bench}
    return measure.finish("overlap", info, t_start, settings, figures, bench["out"], log)


def _rows(runs: dict[str, dict], steps: int) -> dict[str, Any]:
    """Each program's figures: median and best call, env steps/s, host seconds and the ideal."""
    rows: dict[str, Any] = {}
    for name, r in runs.items():
        median, host = statistics.median(r["times"]), statistics.median(r["host_s"])
        rows[name] = {
            "compile_s": r["compile_s"],
            "memory": r["memory"],
            "iteration_s": r["times"],
            "iteration_s_median": median,
            "env_steps_per_s": steps / median,
            "env_steps_per_s_best": steps / min(r["times"]),
            "host_s": r["host_s"],
            "host_s_median": host,
        }
    for name, row in rows.items():
        program, way = name.split("/")
        collect = rows[f"rollout/{way}"] if program == "iteration" else row
        rest = row["iteration_s_median"] - collect["iteration_s_median"]  # the update, for the iteration
        c_host, c_time = collect["host_s_median"], collect["iteration_s_median"]
        row["ideal_s"] = rest + max(c_host, c_time - c_host)
    return rows


def _ratios(rows: dict[str, Any], ways: Sequence[str]) -> dict[str, float]:
    """Each way's rate over one group's (``g1``, or the first way's), and the rollout's and the
    iteration's over that way's raw env."""
    rate = {name: row["env_steps_per_s"] for name, row in rows.items()}
    base = "g1" if "g1" in ways else ways[0]
    ratios = {}
    for way in ways:
        for program in PROGRAMS:
            if way != base:
                ratios[f"{program}/{way}_over_{program}/{base}"] = (
                    rate[f"{program}/{way}"] / rate[f"{program}/{base}"]
                )
        for program in ("rollout", "iteration"):
            ratios[f"{program}/{way}_over_raw/{base}"] = rate[f"{program}/{way}"] / rate[f"raw/{base}"]
    return ratios


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg, rows = result["settings"]["config"], result["rows"]
    runtime = result["runtime_pair_over_sum"]
    lines = [
        f"overlap probe: {cfg['env']} (native physics, {cfg['physics_threads']} thread(s)), "
        f"{cfg['num_envs']} envs x {cfg['unroll_length']} steps, PPO explore={cfg['explore']}, "
        f"{result['settings']['rounds']} rounds interleaved",
        measure.machine_line(result),
        f"XLA runtime: two independent {SLEEP_S * 1e3:.0f} ms host callbacks take "
        f"{runtime['top_level']:.2f} (top level), {runtime['in_scan']:.2f} (in a scan), "
        f"{runtime['two_phase']:.2f} (one on a worker thread, the ring's way) x their sum "
        "(1.0: one after the other, 0.5: at once)",
        "",
        f"  {'program':<15}{'compile s':>10}{'iter s':>9}{'env steps/s':>13}{'best':>9}"
        f"{'host s':>9}{'ideal s':>9}",
    ]
    for name, e in rows.items():
        lines.append(
            f"  {name:<15}{e['compile_s']:>10.1f}{e['iteration_s_median']:>9.3f}"
            f"{e['env_steps_per_s']:>13,.0f}{e['env_steps_per_s_best']:>9,.0f}"
            f"{e['host_s_median']:>9.3f}{e['ideal_s']:>9.3f}"
        )
    lines += [
        "  (iter s, env steps/s and host s: median; best: the fastest call; host s: inside MuJoCo's",
        "  host step; ideal s: the host's seconds or the rest of the rollout, whichever is longer,",
        "  plus the update: the call if the physics overlapped all else in the rollout)",
        "",
        *(f"  {key}: {value:.3f}x" for key, value in result["ratios"].items()),
        f"  load average after each round: {result['load_average_rounds']}",
    ]
    return "\n".join(lines)
