"""The coherent suite's long-chain rows: what the chain costs where it runs long.

Two settings, each timed as its own interleaved pair (action noise, coherent) of the
real jitted PPO iteration, on the suite's task and seed:

* ``thesis``: ``preset=thesis`` (4 envs x 1,000-step buffers scored from the buffer's
  start, up to 80 full-batch policy steps with early stopping, 80 value steps; see
  docs/presets.md). Both strategies stop their policy steps at the same KL target, so
  the ratio includes how many steps each takes (reported as ``policy_steps``).
* ``episode``: the suite's own settings with ``coherent.gradient=episode``: every
  segment's loss re-infers its episode prefix (up to ``episode_length - 1`` steps) under
  the current parameters. Its cost grows with the prefix, so it is timed over whole
  episode cycles (`timed_iterations`) and reported by the mean, not the median.

The ratio coherent / action of env steps per second is the figure each row reports.
"""

from __future__ import annotations

import dataclasses
import statistics
from typing import Any

from coherent_jax.config import Config, ConfigError, parse_overrides, validate

#: the rows, in the order they run
CHAINS = ("thesis", "episode")


def chain_config(cfg: Config, chain: str) -> Config:
    """The config of one long-chain row, built from the suite's ``cfg``."""
    if chain == "thesis":
        return parse_overrides([f"env={cfg.env}", f"seed={cfg.seed}", "algo=ppo", "preset=thesis"])
    if chain == "episode":
        out = dataclasses.replace(cfg, coherent=dataclasses.replace(cfg.coherent, gradient="episode"))
        try:
            validate(dataclasses.replace(out, explore="coherent"))
        except ConfigError as exc:  # a setting the episode gradient refuses: name the row
            raise ConfigError(
                f"invalid value for 'chains': 'episode' does not run with these settings ({exc}) "
                "(allowed: thesis, or none)"
            ) from None
        return out
    raise ValueError(f"unknown chain row {chain!r}; allowed: {', '.join(CHAINS)}")


def timed_iterations(cfg: Config, chain: str, iterations: int) -> int:
    """Iterations to time for a row: ``iterations``, and for the episode row whole episode
    cycles of ceil(episode_length / unroll_length) iterations, as many as cover it. The
    episode row's cost rises with the prefix, which runs through every length once a cycle
    (all envs in step, as on tasks without early termination)."""
    if chain != "episode":
        return iterations
    cycle = -(-cfg.episode_length // cfg.unroll_length)
    return -(-iterations // cycle) * cycle


def bench_chains(cfg: Config, chains: list[str], iterations: int, bench_training, log) -> dict[str, Any]:
    """Times each row with ``bench_training(cfg, n, log, remat_row=False)``
    (`coherent._bench_training`, n = `timed_iterations`); returns per row the config's
    shape, the statistic used (the median; for the episode row the mean over whole
    cycles), the two strategies' iteration seconds by it, env steps/s, policy steps
    applied, and the ratio."""
    results: dict[str, Any] = {}
    for chain in chains:
        row_cfg = chain_config(cfg, chain)
        count = timed_iterations(row_cfg, chain, iterations)
        log(
            f"[bench] long chain '{chain}': {row_cfg.num_envs} envs x {row_cfg.unroll_length} steps, "
            f"{count} timed iterations"
        )
        training, trainers = bench_training(row_cfg, count, log, remat_row=False)
        mean = chain == "episode"
        rate = "env_steps_per_s_total" if mean else "env_steps_per_s"
        row: dict[str, Any] = {
            "num_envs": row_cfg.num_envs,
            "unroll_length": row_cfg.unroll_length,
            "gradient": row_cfg.coherent.gradient,
            "timed_iterations": count,
            "statistic": "mean" if mean else "median",
            "ratio_coherent_over_action": training["coherent"][rate] / training["action"][rate],
        }
        for name in ("action", "coherent"):
            entry = training[name]
            times = entry["iteration_s"]
            row[name] = {
                "iteration_s": statistics.fmean(times) if mean else entry["iteration_s_median"],
                "iteration_s_median": entry["iteration_s_median"],
                "env_steps_per_s": entry[rate],
                "compile_s": entry["compile_s"],
                "policy_steps": statistics.median(entry["updates_applied"]),
            }
        del trainers
        results[chain] = row
    return results


def format_chains(chains: dict[str, Any]) -> list[str]:
    """The table of `bench_chains`'s rows."""
    if not chains:
        return []
    lines = [
        "4. long chains: PPO iteration, action vs coherent (interleaved; the episode row's mean",
        "   over whole episode cycles, the other's median)",
        f"  {'row':<9}{'shape':>13}{'gradient':>10}{'action s':>10}{'coherent s':>12}"
        f"{'policy steps':>14}{'ratio':>8}",
    ]
    for chain, row in chains.items():
        shape = f"{row['num_envs']}x{row['unroll_length']}"
        steps = f"{row['action']['policy_steps']:.0f}/{row['coherent']['policy_steps']:.0f}"
        lines.append(
            f"  {chain:<9}{shape:>13}{row['gradient']:>10}{row['action']['iteration_s']:>10.3f}"
            f"{row['coherent']['iteration_s']:>12.3f}{steps:>14}"
            f"{row['ratio_coherent_over_action']:>7.2f}x"
        )
    return lines
