"""The `classic` suite: PPO on MountainCarContinuous with every exploration strategy.

Gymnasium's ``MountainCarContinuous-v0`` (``env=mountain_car_continuous``, in pure JAX:
`coherent_jax.envs.brax_env`) pays 100 once at the hilltop and charges 0.1 a^2 every step,
so a policy whose exploration never finds the goal learns to stand still, at return 0.
Gaussian action noise rarely finds it; coloured (pink) noise and parameter-space noise
do (Eberhard et al., ICLR 2023; Plappert et al., ICLR 2018). Coherent exploration runs
at three beta, from trajectory-based (beta 0: one draw of the last layer's weights per
episode) towards step-based.

**The coherent gradient.** ``coherent.gradient=episode``: only there does the chain run
on across segments within an episode, so that beta 0 is one draw for the whole 999-step
episode and the loss is the exact gradient of that process (docs/coherent.md). Under
the default ``exact`` the chain restarts at every 64-step segment, so beta 0 would be a
fresh draw every 64 steps (16 per episode), not trajectory-based exploration; ``stored``
runs the chain on but its gradient is not that of any process that ran.

**The budget.** Measured here first, one seed each at small budgets (2 cores shared
with other jobs, load average 8-10): PPO with action noise ran at 41.6k env steps/s with
the default 64 envs and 24.9k with 16; coherent with the episode gradient at beta 0 at
350 env steps/s with 64 envs and 910 with 16 (its loss re-infers each segment's episode
prefix of up to 1,024 steps; why fewer envs run faster per env step was not analysed).
Every cell therefore runs 16 envs (the same for every strategy): 2.6x the coherent
cell's rate, and four PPO iterations per 4,096 env steps where 64 envs run one. The
coherent grid cell itself (15 points vmapped, one episode cycle of 16 iterations) then
ran at 990 env steps/s over all points, about one point's rate, after 35 s of
compilation. At 200k steps per seed (experiments/studies/classic.yaml) (about 12 episodes per env, 195
PPO iterations) that cell needs about 51 minutes, the six other cells about 6 together
at `coherent_jax.study.cost.STRATEGY_COST`, and compiling the seven sweeps at most 10: about 67 minutes
for the suite (`estimated_minutes`), inside 60-90 with room for a busier machine. RL
Baselines3 Zoo trains its tuned PPO (with gSDE) for 20k steps on this task, so 200k
steps leave every strategy room to find the goal and to learn to reach it; a strategy
that has not found it by then is reported as such.

**Goal reached.** The task terminates exactly when the car reaches the flag, so the
runs log the fraction of episodes that did (``train/goal_reached`` among the training
episodes an iteration completed, ``eval/goal_reached`` among the deterministic
evaluation episodes). The report counts, per strategy, the seeds whose exploration ever
reached the goal in training and the seeds whose final policy reaches it in at least one
evaluation episode. (The return says the same: a 999-step episode's return is positive
exactly when it reached the goal, but the logged returns are means over episodes.)
"""

from __future__ import annotations

from pathlib import Path

import reproduce  # beside this file (the suites' study files, experiments/studies/)

from coherent_jax.study import curves, stats, tables
from coherent_jax.study.cell import Cell
from coherent_jax.study.cost import STRATEGY_COST

# What the report reads of the classic cells besides the returns (`coherent_jax.study.curves`).
GOAL_METRICS = (curves.EVAL_GOAL, curves.TRAIN_GOAL)
# Env steps/s at 16 envs measured on this machine (the module's docstring): one seed of
# action noise, and the coherent grid cell over all its points; minutes to compile a cell.
CLASSIC_ACTION_RATE = 24_900.0
CLASSIC_EPISODE_RATE = 990.0
COMPILE_MINUTES = 1.5


def classic_cells() -> list[Cell]:
    """The suite's cells (experiments/studies/classic.yaml): one per strategy (5 seeds), and
    coherent's three beta as one grid cell."""
    return reproduce.select("classic", [])


def goal_rows(cell: Cell, results: Path, label) -> list[str]:
    """Table rows, per strategy (``label(cell, run)``) of a classic cell: the seeds that ever
    reached the goal in training, when they first did, and the seeds whose final policy
    reaches it (in at least one evaluation episode)."""
    final, train = (stats.load_runs(results / cell.suite, cell.name, m) for m in GOAL_METRICS)
    rows = []
    for row, name in zip(
        tables.reach_rows(cell, train, label, task=False),
        sorted({label(cell, r) for r in train}),
        strict=True,
    ):
        reaches = [bool(r.values[-1] > 0.0) for r in final if label(cell, r) == name]
        rows.append(f"{row} {sum(reaches)} of {len(reaches)} |")
    return rows


def classic_lines(done: list[Cell], results: Path, label) -> list[str]:
    """The classic suite's goal table (beside the returns of the cell table)."""
    lines = [
        "Seeds whose exploration ever reached MountainCar's goal (a training episode that",
        "terminated at the flag), the median env step of the first one, and seeds whose",
        "final deterministic policy reaches it in at least one evaluation episode.",
        "",
        "| strategy | seeds that reached it in training | first reached at (median env steps) "
        "| seeds whose final policy reaches it |",
        "|---|---|---|---|",
    ]
    for c in done:
        lines += goal_rows(c, results, label)
    return [*lines, ""]


def estimated_minutes(action_rate: float = CLASSIC_ACTION_RATE) -> float:
    """Minutes the whole suite needs on this machine at the measured rates: the strategies'
    cells at the action rate over their `coherent_jax.study.cost.STRATEGY_COST`, coherent's at
    the episode gradient's rate (vmapped points share the cores: a cell's rate is one
    point's), and each cell's compilation."""
    cells = classic_cells()
    seconds = 60 * COMPILE_MINUTES * len(cells)
    for cell in cells:
        explore = cell.setting("explore")
        cost = STRATEGY_COST.get(explore, 1.0)
        rate = CLASSIC_EPISODE_RATE if explore == "coherent" else action_rate / cost
        seconds += cell.env_steps / rate
    return seconds / 60
