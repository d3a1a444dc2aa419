"""The ``strategies`` suite: ``python -m benchmarks strategies [key=value ...]``.

What each exploration strategy costs per iteration of the same algorithm, settings and
task: the real jitted iteration (`coherent_jax.agents.make_trainer`, the program
``python -m coherent_jax.train`` runs) once per ``explore=`` value, each compiled and
warmed up, then timed interleaved (A B C, C B A, ...) so that a change of load on a
shared machine hits every strategy alike. Per strategy it reports compile time, the
median iteration time, env steps/s, the time relative to the first strategy listed
(``action`` by default), the gradient steps applied per iteration (PPO stops early at a
KL target, so two strategies need not take the same number) and XLA's peak memory.

Settings are every training key except ``explore`` (the suite runs each strategy) and
``sac.warmup_steps`` (with ``algo=sac`` it is 0, so that every timed iteration acts
through the strategy rather than uniformly at random), plus `KEYS`. The results go to a
JSON file (default ``bench_results/strategies.json``), written atomically.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Sequence
from typing import Any

import jax

from benchmarks import IGNORED, measure
from coherent_jax.agents import make_trainer
from coherent_jax.config import Config, ConfigError, cli, to_dict, validate, with_values
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.strategies import EXPLORES, SUPPORTED_ALGOS

_ALL = "all"


def _strategy_list(text: str) -> list[str] | str:
    """``all``, or distinct ``explore=`` values in the order given (the first is the baseline)."""
    return _ALL if text.strip() == _ALL else cli.ordered_choice_list(EXPLORES)(text)


# How long the suite takes at its defaults (`python -m benchmarks --help` prints it).
COST = "~13 min (762 s measured; its seven compiles are most of it)"
KEYS: dict[str, cli.Key] = {
    "strategies": cli.Key(
        _ALL,
        _strategy_list,
        f"all, or a list of distinct {', '.join(EXPLORES)}, e.g. [action,gsde,lattice]",
        "strategies timed, the first the baseline of the ratios (all: every one the algo runs, action first)",
    ),
    "iterations": cli.Key(5, cli.int_at_least(1), "an integer >= 1", "timed iterations per strategy"),
    "out": cli.Key(
        "bench_results/strategies.json", cli.output_file, "a writable file path", "where the JSON goes"
    ),
}
FIXED: dict[str, str | None] = {"explore": None, "sac.warmup_steps": None}


def parse(items: Sequence[str]) -> cli.Parsed:
    """The suite's settings (``strategies`` resolved to a list) and training config.

    Every strategy is checked with the config, so that one the algorithm does not run
    with (NoisyNet with SAC) or a setting one of them refuses stops the suite in one
    line before anything compiles.
    """
    parsed = cli.parse_command(items, KEYS, command="the strategies suite", fixed=FIXED, ignored=IGNORED)
    cfg = parsed.config
    names = parsed.settings["strategies"]
    if names == _ALL:
        names = [s for s in EXPLORES if cfg.algo in SUPPORTED_ALGOS[s]]
    for name in names:
        try:
            validate(_strategy_config(cfg, name))
        except ConfigError as exc:
            raise ConfigError(f"invalid value for 'strategies': {name!r} does not run here ({exc})") from None
    parsed.settings["strategies"] = names
    return parsed


def _strategy_config(cfg: Config, explore: str) -> Config:
    """``cfg`` with ``explore``; SAC without its uniform warm-up."""
    values: dict[str, Any] = {"explore": explore}
    if cfg.algo == "sac":
        values["sac.warmup_steps"] = 0
    return with_values(cfg, values)


def _compile_all(cfg: Config, names: Sequence[str], log) -> dict[str, dict]:
    """Each strategy's trainer, initial state and compiled iteration, warmed up by one call."""
    # One env for every trainer (an MJX model takes seconds to build); no evaluation runs here.
    env = VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    runs: dict[str, dict] = {}
    for name in names:
        trainer = make_trainer(_strategy_config(cfg, name), env=env, eval_env=env)
        state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
        what = f"the {cfg.algo} iteration, explore={name}"
        runs[name] = measure.warm_iteration(trainer.iteration, state, log, what)
        runs[name]["updates_applied"] = []
    return runs


def bench_strategies(cfg: Config, names: Sequence[str], iterations: int, log) -> dict[str, Any]:
    """Compiles every strategy's iteration, times them interleaved; returns the figures per strategy."""
    runs = _compile_all(cfg, names, log)

    def count_updates(name: str, metrics: dict) -> None:
        runs[name]["updates_applied"].append(float(metrics["train/updates_applied"]))

    measure.time_interleaved(runs, list(names), iterations, log, count_updates)
    steps = cfg.steps_per_iteration
    base = statistics.median(runs[names[0]]["times"])
    figures: dict[str, Any] = {"env_steps_per_iteration": steps, "baseline": names[0], "rows": {}}
    for name in names:
        run = runs[name]
        median = statistics.median(run["times"])
        figures["rows"][name] = {
            "compile_s": run["compile_s"],
            "warmup_call_s": run["warmup_call_s"],
            "memory": run["memory"],
            "iteration_s": run["times"],
            "iteration_s_median": median,
            "env_steps_per_s": steps / median,
            "time_over_baseline": median / base,
            "updates_applied": run["updates_applied"],
            "updates_applied_median": statistics.median(run["updates_applied"]),
        }
    return figures


def run(items: Sequence[str], log: Callable[[str], None] = measure.print_log) -> dict:
    """Runs the suite with ``key=value`` items; writes and returns the results.

    Raises `ConfigError` for bad input before anything runs.
    """
    bench, cfg, _ = parse(items)
    info, t_start = measure.start("strategies", log)
    figures = {"training": bench_strategies(cfg, bench["strategies"], bench["iterations"], log)}
    settings = {"config": to_dict(cfg), **bench}
    return measure.finish("strategies", info, t_start, settings, figures, bench["out"], log)


def format_table(result: dict) -> str:
    """The human-readable summary of `run`'s result."""
    cfg, tr = result["settings"]["config"], result["training"]
    rows = tr["rows"]
    first = next(iter(rows.values()))
    lines = [
        f"strategies bench: {cfg['algo']} on {cfg['env']}, {cfg['num_envs']} envs x "
        f"{cfg['unroll_length']} steps = {tr['env_steps_per_iteration']} env steps per iteration"
        + (f", preset={cfg['preset']}" if cfg.get("preset") else ""),
        measure.machine_line(result),
        f"median of {len(first['iteration_s'])} interleaved iterations; time relative to {tr['baseline']}",
        "",
        f"  {'strategy':<10}{'compile s':>10}{'iter s':>9}{'env steps/s':>13}{'time x':>8}"
        f"{'grad steps':>12}{'peak MB':>10}",
    ]
    for name, e in rows.items():
        lines.append(
            f"  {name:<10}{e['compile_s']:>10.1f}{e['iteration_s_median']:>9.3f}"
            f"{e['env_steps_per_s']:>13,.0f}{e['time_over_baseline']:>8.2f}{e['updates_applied_median']:>12.0f}{measure.peak_mb(e['memory']):>10}"
        )
    return "\n".join(lines)
