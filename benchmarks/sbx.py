"""The ``sbx`` suite: our SAC beside SBX's, ``python -m benchmarks sbx [key=value ...]``.

SBX (``sbx-rl``, the JAX Stable-Baselines) is the SAC trainer an SB3 user would pick. The
suite trains both on the same Gymnasium MuJoCo task with the same settings (`IDENTICAL`;
what cannot be the same is `NOT_IDENTICAL`) and times them alternately:

- ours: `SACTrainer.iteration` compiled once (compile time apart), in this process;
- SBX's: ``sbx.SAC`` on a ``DummyVecEnv`` of ``num_envs`` Gymnasium envs, in its own
  process with its own venv (`benchmarks.sbx_process`, made on first use from
  ``benchmarks/sbx-requirements.txt``), driven by ``benchmarks/sbx_driver.py``;
- after the same warm-up on both sides (`warmup_iterations`: random actions until the
  updates start, then two iterations more, which compile), ``rounds`` rounds of
  ``iterations`` iterations per side, the order flipped every round so that a change of
  load hits both;
- env steps/s and gradient updates/s of each side (the median iteration), their ratio
  ours / SBX, and the ratio in every round with its median;
- where the time goes: SBX's collection and training, timed apart within each iteration;
  ours' collection by the same program with its updates switched off (as the ``sac``
  suite does), its updates as the difference; the ratios of each part;
- compile times apart: ours' programs' compilation; SBX's the time its warm-up
  iterations took above its median iteration.

Settings are every training key (``algo=sac`` and ``explore=action`` are set by the suite)
plus `KEYS`; `sbx_settings` maps ours to SBX's arguments. Results go to a JSON file
(default ``bench_results/sbx.json``), written atomically.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax

from benchmarks import IGNORED, measure, sbx_process
from coherent_jax.agents.sac import SACTrainer
from coherent_jax.config import Config, ConfigError, cli, to_dict, with_values
from coherent_jax.envs.registry import EPISODE_LENGTH, SHORT_NAMES, resolve_physics
from coherent_jax.envs.vec_env import VecEnv

# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~8 min (449 s measured 2026-12-07, load average 11-12) once the venv exists; making it took 7.7 min"
KEYS: dict[str, cli.Key] = {
    "rounds": cli.Key(
        3, cli.int_at_least(1), "an integer >= 1", "alternations of the two sides (the order flips)"
    ),
    "iterations": cli.Key(5, cli.int_at_least(1), "an integer >= 1", "iterations timed per side and round"),
    "venv": cli.Key(
        sbx_process.DEFAULT_VENV,
        cli.text_value,
        "a folder",
        "SBX's venv (relative to the repository's root), made from benchmarks/sbx-requirements.txt",
    ),
    "install": cli.Key(
        True, cli.boolean, "true or false", "create or update the venv if needed (false: refuse without it)"
    ),
    "out": cli.Key("bench_results/sbx.json", cli.output_file, "a writable file path", "where the JSON goes"),
}
FIXED: dict[str, str | None] = {"algo": "sac", "explore": "action"}  # plain SAC, as SBX's
# HalfCheetah-v5 with SAC's defaults, but a replay buffer of 100k transitions (its size does not
# change the cost of an iteration, only the memory of both sides) and no random-action warm-up
# (the updates run from the first iteration, so the warm-up is short).
CONFIG_DEFAULTS = ("env=halfcheetah", "sac.buffer_size=100000", "sac.warmup_steps=0")

IDENTICAL = (
    "the task: Gymnasium's MuJoCo v5 task (the same MJCF model and MuJoCo 4.0.0's float64 step, "
    "reward and termination; tests/test_gymnasium_tasks.py holds ours to Gymnasium step for step), "
    "its time limit, and truncation bootstrapped (SB3's handle_timeout_termination)",
    "num_envs envs, num_envs x unroll_length env steps per iteration (train_freq=(unroll_length, 'step') "
    "of a vectorized env of num_envs) and utd_ratio times as many gradient updates (gradient_steps)",
    "batch size, replay capacity in transitions, and learning starts: uniform random actions "
    "until sac.warmup_steps, updates from the iteration that reaches it on (learning_starts = "
    "warmup_steps - 1, as SB3 trains once num_timesteps > learning_starts)",
    "the networks: an actor trunk policy_hidden with a linear mean and a state-dependent log-std head, "
    "tanh-squashed Gaussian; twin critics value_hidden on [s; a]; the activation",
    "the update: Adam (0.9, 0.999, 1e-8) at lr for actor and critics, the target from the current "
    "actor and the twin target critics, the actor on the updated critics every update "
    "(policy_delay=1), Polyak tau every update, gamma, the temperature fixed (ent_coef) or "
    "tuned to the same target entropy",
    "float32 networks on JAX 0.9.2's XLA, on the same CPU, one physics thread each",
)
NOT_IDENTICAL = (
    "collection: ours steps native MuJoCo from inside the jitted iteration (one host callback per "
    "vector step, the actor in the same program); SBX steps Gymnasium's Python envs one after the "
    "other in a DummyVecEnv and calls its jitted actor from Python every vector step. That "
    "difference is what the comparison is about",
    "replay: ours is a ring buffer in the jitted state, sampled inside the update loop; SB3's is a "
    "NumPy buffer (float64 observations, as Gymnasium gives them) sampled on the host, "
    "batch_size x gradient_steps transitions at once per iteration, then copied in",
    "an iteration is one compiled program (ours) against Python's loop of collect_rollouts and one "
    "jitted fori_loop of the updates whose losses are read back to the host (SBX)",
    "the actor's distribution code: ours writes tanh(N(mu, sigma)) and its log-density by hand; SBX "
    "uses TFP's TanhTransformedDistribution of a MultivariateNormalDiag, log std clipped to [-20, 2]",
    "SBX halves the critics' squared error (a scale, not a cost), moves the targets between the "
    "critics' and the actor's step (ours after both), and with a fixed ent_coef still takes an "
    "Adam step on a constant temperature",
    "initialisation (ours orthogonal, SBX Flax's LeCun normal) and the random streams: the "
    "suite compares speed, not learning",
)


def gym_id(env: str) -> str | None:
    """The Gymnasium id of one of Gymnasium's MuJoCo v5 tasks (``halfcheetah`` -> ``HalfCheetah-v5``)."""
    if env in SHORT_NAMES:
        return SHORT_NAMES[env]
    return env if env in SHORT_NAMES.values() else None


def check_comparable(cfg: Config) -> None:
    """Refuses, with a `ConfigError`, a setting that has no counterpart in SBX's SAC."""
    if gym_id(cfg.env) is None:
        raise ConfigError(
            f"invalid env {cfg.env!r} for the sbx suite: SBX trains Gymnasium's tasks, "
            f"so it must be one of Gymnasium's MuJoCo v5 tasks ({', '.join(SHORT_NAMES)} or their ids)"
        )
    if cfg.normalize_obs:
        raise ConfigError(
            "invalid key 'normalize_obs': SBX's SAC does not normalise observations (allowed: false)"
        )
    if cfg.sac.update_after is not None and cfg.sac.update_after != cfg.sac.warmup_steps:
        raise ConfigError(
            "invalid key 'sac.update_after': SB3 has one learning_starts for random actions and "
            "updates alike (allowed: null or sac.warmup_steps)"
        )


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and SAC config; `ConfigError` in one line for bad input.

    Refused here, before anything runs: a setting SBX has no counterpart for
    (`check_comparable`), and ``install=false`` when the venv is not ready.
    """
    parsed = cli.parse_command(
        items,
        KEYS,
        command="the sbx suite",
        fixed=FIXED,
        config_defaults=CONFIG_DEFAULTS,
        ignored=IGNORED,
    )
    check_comparable(parsed.config)
    venv = sbx_process.venv_path(parsed.settings["venv"])
    if not parsed.settings["install"] and not sbx_process.venv_ready(venv):
        raise ConfigError(
            f"invalid key 'venv': {venv} is not SBX's venv with benchmarks/sbx-requirements.txt "
            "installed, and install=false (allowed: install=true, which makes it)"
        )
    return parsed


def warmup_iterations(cfg: Config) -> int:
    """Untimed iterations on both sides: up to the first that updates (the one whose collection
    reaches ``sac.warmup_steps``), which compiles SBX's updates, and two more (SBX's actor
    compiles again for trained parameters)."""
    return max(math.ceil(cfg.sac.warmup_steps / cfg.steps_per_iteration), 1) + 2


def sbx_settings(cfg: Config) -> dict[str, Any]:
    """What the driver builds SBX's SAC with: ``cfg``'s values under SBX's names (`IDENTICAL`)."""
    env_id = gym_id(cfg.env)
    assert env_id is not None, cfg.env  # check_comparable refuses the others
    temperature = float(cfg.sac.temperature)
    target = cfg.sac.target_entropy
    return {
        "env_id": env_id,
        "num_envs": cfg.num_envs,
        "episode_length": cfg.episode_length or EPISODE_LENGTH[env_id],
        "seed": cfg.seed,
        "warmup_iterations": warmup_iterations(cfg),
        "sac": {
            "learning_rate": float(cfg.lr),  # actor, critics and temperature, as ours
            "buffer_size": cfg.sac.buffer_size,
            # SB3 acts at random while num_timesteps < learning_starts and trains once
            # num_timesteps > learning_starts; ours acts at random while env steps < warmup_steps
            # and trains once they are >= it.
            "learning_starts": max(cfg.sac.warmup_steps - 1, 0),
            "batch_size": cfg.sac.batch_size,
            "tau": float(cfg.sac.tau),
            "gamma": float(cfg.gamma),
            "train_freq": [cfg.unroll_length, "step"],  # vector steps of num_envs envs
            "gradient_steps": cfg.updates_per_iteration,
            "policy_delay": 1,
            "ent_coef": f"auto_{temperature}" if cfg.sac.auto_temperature else temperature,
            "target_entropy": "auto" if target is None else float(target),
            "policy_kwargs": {
                "net_arch": {"pi": list(cfg.policy_hidden), "qf": list(cfg.value_hidden)},
                "activation_fn": cfg.activation,
            },
        },
    }


def held_mismatches(settings: dict[str, Any], held: dict[str, Any], action_size: int) -> list[str]:
    """How the SAC SBX built (the driver's ``held``) differs from ``settings``; empty when it does not."""
    sac = settings["sac"]
    target = -float(action_size) if sac["target_entropy"] == "auto" else sac["target_entropy"]
    want = {
        "n_envs": settings["num_envs"],
        "env_steps_per_iteration": settings["num_envs"] * sac["train_freq"][0],
        "gradient_steps": sac["gradient_steps"],
        "batch_size": sac["batch_size"],
        "buffer_size": sac["buffer_size"],
        "learning_starts": sac["learning_starts"],
        "learning_rate": sac["learning_rate"],
        "qf_learning_rate": sac["learning_rate"],
        "gamma": sac["gamma"],
        "tau": sac["tau"],
        "policy_delay": 1,
        "ent_coef": sac["ent_coef"],
        "target_entropy": target,
        "net_arch_pi": sac["policy_kwargs"]["net_arch"]["pi"],
        "net_arch_qf": sac["policy_kwargs"]["net_arch"]["qf"],
        "n_critics": 2,
        "activation_fn": sac["policy_kwargs"]["activation_fn"],
        "max_episode_steps": settings["episode_length"],
    }
    return [f"{k}: SBX holds {held.get(k)!r}, not {v!r}" for k, v in want.items() if held.get(k) != v]


def _ours(cfg: Config, env: VecEnv, warmup: int, log) -> dict[str, Any]:
    """Our SAC iteration on ``env``, and the same program with the updates switched off
    (collection alone, as in the ``sac`` suite), each compiled and called ``warmup`` times
    untimed."""
    runs: dict[str, Any] = {}
    for mode, values in (("iteration", {}), ("collect_only", {"sac.warmup_steps": 2**31 - 1})):
        trainer = SACTrainer(with_values(cfg, values), env=env, eval_env=env)
        state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
        run = measure.warm_iteration(trainer.iteration, state, log, f"our SAC {mode.replace('_', ' ')}")
        t0 = time.perf_counter()
        for _ in range(warmup - 1):
            run["state"], _ = jax.block_until_ready(run["step"](run["state"]))
        run["warmup_call_s"] += time.perf_counter() - t0
        runs[mode] = run
    return runs


def _time_ours(run: dict[str, Any], iterations: int, updates: int) -> list[float]:
    """Seconds of each of ``iterations`` calls of ``run``'s program, which must apply ``updates`` updates."""
    times = []
    for _ in range(iterations):
        t0 = time.perf_counter()
        run["state"], metrics = jax.block_until_ready(run["step"](run["state"]))
        times.append(time.perf_counter() - t0)
        applied = float(metrics["train/updates_applied"])
        if applied != updates:
            raise RuntimeError(f"our iteration applied {applied} updates, not {updates}")
    return times


def _alternate(ours, driver, cfg: Config, rounds: int, iterations: int, log) -> tuple[list, list]:
    """``rounds`` rounds of ``iterations`` iterations per side, ours first in even rounds.

    Each side's record of a round: ``iteration_s`` and ``collect_s`` (ours: as many calls of
    the collection alone; SBX: its collection within each iteration), and SBX's ``train_s``.
    """
    steps, updates = cfg.steps_per_iteration, cfg.updates_per_iteration
    ours_rounds: list[dict[str, Any]] = []
    sbx_rounds: list[dict[str, Any]] = []
    for r in range(rounds):
        for side in ("ours", "sbx") if r % 2 == 0 else ("sbx", "ours"):
            if side == "ours":
                record = {
                    "iteration_s": _time_ours(ours["iteration"], iterations, updates),
                    "collect_s": _time_ours(ours["collect_only"], iterations, 0),
                }
                ours_rounds.append(record)
            else:
                record = driver.run(iterations)
                if record["updates"] != iterations * updates or len(record["iteration_s"]) != iterations:
                    done = f"{record['updates']} updates in {len(record['iteration_s'])} iterations"
                    raise RuntimeError(f"SBX ran {done}, not {iterations * updates} in {iterations}")
                sbx_rounds.append(record)
            took = sum(record["iteration_s"])
            rate = iterations * steps / took
            log(f"[bench] round {r + 1}/{rounds} {side}: {rate:,.1f} env steps/s ({took:.1f} s)")
    return ours_rounds, sbx_rounds


def _side(steps: int, updates: int, rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """One side's medians and rates from its rounds' ``iteration_s`` and ``collect_s``."""
    median = lambda key: statistics.median([t for r in rounds for t in r[key]])  # noqa: E731
    t_iteration, t_collect = median("iteration_s"), median("collect_s")
    # SBX times its training; ours is the iteration less its collection (as the sac suite's).
    t_update = median("train_s") if "train_s" in rounds[0] else max(t_iteration - t_collect, 1e-9)
    return {
        "iteration_s": [r["iteration_s"] for r in rounds],
        "collect_s": [r["collect_s"] for r in rounds],
        "iteration_s_median": t_iteration,
        "collect_s_median": t_collect,
        "update_s_median": t_update,
        "env_steps_per_s": steps / t_iteration,
        "gradient_updates_per_s": updates / t_iteration,
        "collect_env_steps_per_s": steps / t_collect,
        "update_only_updates_per_s": updates / t_update,
        "round_env_steps_per_s": [steps * len(r["iteration_s"]) / sum(r["iteration_s"]) for r in rounds],
    }


def summarize(
    steps: int,
    updates: int,
    ours: dict[str, Any],
    ours_rounds: list[dict[str, Any]],
    sbx_ready: dict[str, Any],
    sbx_rounds: list[dict[str, Any]],
) -> dict[str, Any]:
    """The figures of both sides and their ratios ours / SBX from the timed iterations (pure).

    ``ours``: each program's ``compile_s``, ``warmup_call_s`` and ``memory`` under
    ``iteration`` and ``collect_only``; ``ours_rounds`` and ``sbx_rounds``: each round's
    record (`_alternate`); ``sbx_ready``: the driver's ready record.
    """
    o, x = _side(steps, updates, ours_rounds), _side(steps, updates, sbx_rounds)
    o.update(
        compile_s=ours["iteration"]["compile_s"],
        compile_collect_only_s=ours["collect_only"]["compile_s"],
        warmup_call_s=ours["iteration"]["warmup_call_s"],
        memory=ours["iteration"]["memory"],
    )
    warm = sbx_ready["warmup"]["iteration_s"]
    x.update(
        train_s=[r["train_s"] for r in sbx_rounds],
        # The warm-up iterations' time above the median iteration: the actor's and the
        # updates' compilation (random-action iterations, cheaper, count as nothing).
        compile_s=sum(max(0.0, t - x["iteration_s_median"]) for t in warm),
        setup_s=sbx_ready["setup_s"],
        warmup_iteration_s=warm,
        versions=sbx_ready["versions"],
        held=sbx_ready["held"],
    )
    pairs = zip(ours_rounds, sbx_rounds, strict=True)
    round_ratios = [sum(b["iteration_s"]) / sum(a["iteration_s"]) for a, b in pairs]
    ratio = x["iteration_s_median"] / o["iteration_s_median"]
    return {
        "env_steps_per_iteration": steps,
        "updates_per_iteration": updates,
        "ours": o,
        "sbx": x,
        # The same counts per iteration on both sides: one ratio for env steps/s and updates/s.
        "ratio_env_steps_per_s": ratio,
        "ratio_gradient_updates_per_s": ratio,
        "ratio_collect": x["collect_s_median"] / o["collect_s_median"],
        "ratio_updates_alone": x["update_s_median"] / o["update_s_median"],
        "round_ratios": round_ratios,
        "round_ratio_median": statistics.median(round_ratios),
    }


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results.

    Raises `ConfigError` for bad input before anything runs; makes SBX's venv first if needed.
    """
    bench, cfg, _ = parse(items)
    python = sbx_process.ensure_venv(sbx_process.venv_path(bench["venv"]), log)
    info, t_start = measure.start("sbx", log)
    settings = sbx_settings(cfg)
    warmup = settings["warmup_iterations"]
    log(f"[bench] SBX's SAC: building and {warmup} warm-up iterations in {python} ...")
    with sbx_process.Driver(python, settings) as driver:
        warm_s = ", ".join(f"{t:.1f}" for t in driver.ready["warmup"]["iteration_s"])
        log(f"[bench]   ready: setup {driver.ready['setup_s']:.1f} s, warm-up iterations {warm_s} s")
        env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
        wrong = held_mismatches(settings, driver.ready["held"], env.action_size)
        if wrong:
            raise RuntimeError("SBX's SAC differs from the settings: " + "; ".join(wrong))
        ours = _ours(cfg, env, warmup, log)
        ours_rounds, sbx_rounds = _alternate(ours, driver, cfg, bench["rounds"], bench["iterations"], log)
    figures = {
        "training": summarize(
            cfg.steps_per_iteration, cfg.updates_per_iteration, ours, ours_rounds, driver.ready, sbx_rounds
        ),
        "sbx_settings": settings,
        "physics": resolve_physics(cfg.env, cfg.physics),
        "identical": list(IDENTICAL),
        "not_identical": list(NOT_IDENTICAL),
    }
    return measure.finish("sbx", info, t_start, {"config": to_dict(cfg), **bench}, figures, bench["out"], log)


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg, tr, s = result["settings"]["config"], result["training"], result["sbx_settings"]
    hidden = lambda h: "[" + ",".join(map(str, h)) + "]"  # noqa: E731
    o, x = tr["ours"], tr["sbx"]
    lines = [
        f"sbx bench: {s['env_id']} ({result['physics']} physics for ours), {cfg['num_envs']} envs x "
        f"{cfg['unroll_length']} steps = {tr['env_steps_per_iteration']} env steps and "
        f"{tr['updates_per_iteration']} updates (batch {cfg['sac']['batch_size']}) per iteration, actor "
        f"{hidden(cfg['policy_hidden'])}, critics 2 x {hidden(cfg['value_hidden'])} {cfg['activation']}, "
        f"buffer {cfg['sac']['buffer_size']}, warm-up {cfg['sac']['warmup_steps']} steps",
        measure.machine_line(result),
        f"SBX {x['versions'].get('sbx-rl')} (SB3 {x['versions'].get('stable_baselines3')}, "
        f"{x['held']['vec_env']}); {len(tr['round_ratios'])} rounds x {len(o['iteration_s'][0])} "
        "iterations per side, alternated; medians",
        "",
        f"  {'':<6}{'compile s':>10}{'iter s':>9}{'env steps/s':>13}{'updates/s':>11}"
        f"{'collect s':>11}{'update s':>10}",
    ]
    for label, e in (("ours", o), ("SBX", x)):
        lines.append(
            f"  {label:<6}{e['compile_s']:>10.1f}{e['iteration_s_median']:>9.3f}"
            f"{e['env_steps_per_s']:>13,.1f}{e['gradient_updates_per_s']:>11,.1f}"
            f"{e['collect_s_median']:>11.3f}{e['update_s_median']:>10.3f}"
        )
    lines += [
        f"  ours / SBX: {tr['ratio_env_steps_per_s']:.2f}x env steps/s and "
        f"{tr['ratio_gradient_updates_per_s']:.2f}x updates/s; per round "
        + ", ".join(f"{r:.2f}" for r in tr["round_ratios"])
        + f" (median {tr['round_ratio_median']:.2f}x); collection alone {tr['ratio_collect']:.2f}x, "
        f"updates alone {tr['ratio_updates_alone']:.2f}x",
        "  (ours' collection is the iteration without its updates, timed apart; what is identical "
        "and what is not: the JSON's 'identical' and 'not_identical')",
    ]
    return "\n".join(lines)
