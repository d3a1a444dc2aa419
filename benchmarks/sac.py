"""SAC benchmark: ``python -m benchmarks sac [key=value ...]``.

Measures, in one process on one set of settings, the real jitted SAC iteration
(`SACTrainer.iteration`: collect ``num_envs x unroll_length`` env steps into the
replay buffer, then ``updates_per_iteration`` gradient updates, then the
strategy's adaptation) with ``explore=action`` (SAC) and ``explore=coherent``
(Coherent-SAC):

- compile time, apart from the steady state;
- env steps/s and gradient updates/s of the whole iteration: the median of
  iterations timed interleaved (A B, B A, ...) so that a load change on a shared
  machine hits both strategies;
- the same program with updates switched off (warm-up never ends), which times
  collection alone; the difference gives the updates' own rate;
- peak memory of each compiled iteration (XLA's ``memory_analysis()``), the
  replay buffer included.

Settings are every training key (``algo`` is sac, ``explore`` and ``sac.warmup_steps``
are set by the suite) plus `KEYS`. Results go to a JSON file
(default ``bench_results/sac.json``), written atomically.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Callable, Sequence
from typing import Any

import jax

from benchmarks import IGNORED, measure
from coherent_jax.agents.sac import SACTrainer
from coherent_jax.config import Config, cli, to_dict, validate, with_values
from coherent_jax.envs.vec_env import VecEnv

# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~4 min (243 s measured)"
KEYS: dict[str, cli.Key] = {
    "iterations": cli.Key(
        5, cli.int_at_least(1), "an integer >= 1", "timed iterations per strategy and mode"
    ),
    "out": cli.Key("bench_results/sac.json", cli.output_file, "a writable file path", "where the JSON goes"),
}
# SAC, with the strategy and the warm-up set per measured program.
FIXED: dict[str, str | None] = {"algo": "sac", "explore": None, "sac.warmup_steps": "0"}
# Halfcheetah with SAC's defaults, but a replay buffer of 100k transitions: the
# buffer's size does not change the cost of an iteration, only its memory.
CONFIG_DEFAULTS = ("env=halfcheetah", "sac.buffer_size=100000")
STRATEGIES = ("action", "coherent")  # SAC and Coherent-SAC


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings and SAC config; `ConfigError` in one line for bad input.

    The config is checked with each strategy the suite runs, so that a setting
    Coherent-SAC refuses stops the suite before it compiles anything.
    """
    parsed = cli.parse_command(
        items, KEYS, command="the sac suite", fixed=FIXED, config_defaults=CONFIG_DEFAULTS, ignored=IGNORED
    )
    for explore in STRATEGIES:
        validate(dataclasses.replace(parsed.config, explore=explore))
    return parsed


def _bench(cfg: Config, iterations: int, log) -> dict:
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    runs: dict[str, dict] = {}
    for explore in STRATEGIES:
        for mode, warmup in (("iteration", 0), ("collect_only", 2**31 - 1)):
            name = f"{explore}/{mode}"
            run_cfg = with_values(cfg, {"explore": explore, "sac.warmup_steps": warmup})
            trainer = SACTrainer(run_cfg, env=env, eval_env=env)
            state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
            what = f"the SAC {mode.replace('_', ' ')}, explore={explore}"
            runs[name] = measure.warm_iteration(trainer.iteration, state, log, what)

    def count_updates(name: str, metrics: dict) -> None:
        if name.endswith("/iteration"):
            runs[name].setdefault("updates_applied", []).append(float(metrics["train/updates_applied"]))

    measure.time_interleaved(runs, list(runs), iterations, log, count_updates)

    steps, updates = cfg.steps_per_iteration, cfg.updates_per_iteration
    results: dict[str, Any] = {"env_steps_per_iteration": steps, "updates_per_iteration": updates}
    for explore in STRATEGIES:
        full, collect = runs[f"{explore}/iteration"], runs[f"{explore}/collect_only"]
        if any(u != updates for u in full["updates_applied"]):
            raise RuntimeError(
                f"{explore}: an iteration applied {full['updates_applied']} updates, not {updates}"
            )
        t_full, t_collect = statistics.median(full["times"]), statistics.median(collect["times"])
        t_updates = max(t_full - t_collect, 1e-9)
        results[explore] = {
            "compile_s": full["compile_s"],
            "compile_collect_only_s": collect["compile_s"],
            "memory": full["memory"],
            "iteration_s": full["times"],
            "collect_only_s": collect["times"],
            "iteration_s_median": t_full,
            "collect_only_s_median": t_collect,
            "env_steps_per_s": steps / t_full,
            "gradient_updates_per_s": updates / t_full,
            "collect_env_steps_per_s": steps / t_collect,
            "update_only_updates_per_s": updates / t_updates,
        }
    a, c = results["action"], results["coherent"]
    results["ratio_coherent_over_action"] = c["env_steps_per_s"] / a["env_steps_per_s"]
    results["ratio_collect_coherent_over_action"] = (
        c["collect_env_steps_per_s"] / a["collect_env_steps_per_s"]
    )
    return results


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results.

    Raises `ConfigError` for bad input before anything runs.
    """
    bench, cfg, _ = parse(items)
    info, t_start = measure.start("sac", log)
    figures = {"training": _bench(cfg, bench["iterations"], log)}
    settings = {"config": to_dict(cfg), **bench}
    return measure.finish("sac", info, t_start, settings, figures, bench["out"], log)


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg, tr = result["settings"]["config"], result["training"]
    hidden = ",".join(map(str, cfg["policy_hidden"]))
    lines = [
        f"sac bench: {cfg['env']}, {cfg['num_envs']} envs x {cfg['unroll_length']} steps = "
        f"{tr['env_steps_per_iteration']} env steps and {tr['updates_per_iteration']} updates "
        f"(batch {cfg['sac']['batch_size']}) per iteration, networks [{hidden}], "
        f"coherent.beta={cfg['coherent']['beta']}",
        measure.machine_line(result),
        f"median of {len(tr['action']['iteration_s'])} interleaved iterations",
        "",
        f"  {'':<10}{'compile s':>10}{'iter s':>9}{'env steps/s':>13}{'updates/s':>11}"
        f"{'collect-only steps/s':>22}{'update-only upd/s':>19}{'peak MB':>10}",
    ]
    for name, label in (("action", "SAC"), ("coherent", "Coh-SAC")):
        e = tr[name]
        lines.append(
            f"  {label:<10}{e['compile_s']:>10.1f}{e['iteration_s_median']:>9.3f}"
            f"{e['env_steps_per_s']:>13,.0f}{e['gradient_updates_per_s']:>11,.0f}{e['collect_env_steps_per_s']:>22,.0f}"
            f"{e['update_only_updates_per_s']:>19,.0f}{measure.peak_mb(e['memory']):>10}"
        )
    lines.append(
        f"  Coherent-SAC / SAC: {tr['ratio_coherent_over_action']:.2f}x (collection alone "
        f"{tr['ratio_collect_coherent_over_action']:.2f}x)"
    )
    return "\n".join(lines)
