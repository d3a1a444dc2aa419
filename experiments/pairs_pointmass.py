"""Every (algo, explore) pair on pointmass: trains the valid ones, prints the table.

usage: python experiments/pairs_pointmass.py [STEPS] [SEEDS] [OUT] [ALGOS]
  STEPS  env steps per run (default 51200 = the test's 100 iterations)
  SEEDS  comma-separated seeds (default 0)
  OUT    JSON output (default runs/pairs-pointmass.json)
  ALGOS  comma-separated algorithms (default: all)

Each valid pair runs through `coherent_jax.train.train` (the CLI's code path) with
the settings of tests/test_pairs.py; a refused pair is listed with the one-line
reason the CLI gives. Prints a markdown table (mean train return of the first and
last quarter of the run, final deterministic eval return over 64 episodes) and writes
the rows to OUT as JSON.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from coherent_jax import strategies
from coherent_jax.config import ALGOS, ConfigError, parse_overrides
from coherent_jax.run.training import train

BASE = [
    "env=pointmass",
    "episode_length=50",
    "num_envs=16",
    "unroll_length=32",
    "ppo.num_minibatches=4",
    "eval_episodes=64",
    "eval_every=0",
    "progress=false",
]
# SAC runs the settings of tests/test_sac.py (100-step episodes, 10,240 env steps,
# UTD 0.5) whatever STEPS says: SAC's updates cost far more per env step.
ALGO_EXTRA = {
    "ppo": [],
    "a2c": ["lr=3e-3"],
    "sac": [
        "episode_length=100",
        "num_envs=8",
        "unroll_length=16",
        "policy_hidden=[64,64]",
        "value_hidden=[64,64]",
        "sac.warmup_steps=1024",
        "sac.utd_ratio=0.5",
        "total_steps=10240",
    ],
}
MC = ["coherent.beta=0.1", "coherent.action_std=0.3", "coherent.w_std_init=0.01"]
MC_ALL = ["coherent.beta=0.1", "coherent.action_std=0.3", "coherent.w_std_init=0.03"]
# Settings under which a strategy or variant learns on pointmass (none: its defaults).
EXTRA = {"coherent": ["coherent.beta=0.1"], "coherent-mc": MC, "coherent-all": MC_ALL}
# Every strategy of the registry and each of its variants: (label, its settings, EXTRA's).
STRATEGIES = [
    (name.replace("-", " "), list(strategies.overrides(name)), EXTRA.get(name, []))
    for s in strategies.STRATEGIES
    for name in (s.name, *s.variants)
]


def overrides_for(algo: str, explore: list[str], extra: list[str], steps: int, seed: int) -> list[str]:
    return [
        *BASE,
        f"algo={algo}",
        *explore,
        *extra,
        f"total_steps={steps}",
        *ALGO_EXTRA[algo],
        f"seed={seed}",
    ]


def main(argv: list[str]) -> int:
    steps = int(argv[0]) if argv else 51200
    seeds = [int(s) for s in (argv[1] if len(argv) > 1 else "0").split(",")]
    out = Path(argv[2] if len(argv) > 2 else "runs/pairs-pointmass.json")
    algos = argv[3].split(",") if len(argv) > 3 else list(ALGOS)
    rows = []
    for name, explore, extra in STRATEGIES:
        for algo in algos:
            try:
                cfgs = [parse_overrides(overrides_for(algo, explore, extra, steps, s)) for s in seeds]
            except ConfigError as exc:
                rows.append({"algo": algo, "explore": name, "refused": str(exc)})
                print(f"[pairs] {algo} {name}: refused: {exc}", flush=True)
                continue
            early, late, evals, wall = [], [], [], 0.0
            for cfg in cfgs:
                history = []
                t0 = time.perf_counter()
                summary = train(cfg, None, progress_fn=lambda i, m, h=history: h.append(m))
                wall += time.perf_counter() - t0
                ret = np.array([m["train/episode_return"] for m in history])
                k = max(1, len(ret) // 4)
                early.append(float(np.nanmean(ret[:k])))
                late.append(float(np.nanmean(ret[-k:])))
                evals.append(float(summary["final_eval_return"]))
            row = {
                "algo": algo,
                "explore": name,
                "overrides": overrides_for(algo, explore, extra, steps, seeds[0]),
                "seeds": seeds,
                "train_return_first_quarter": float(np.mean(early)),
                "train_return_last_quarter": float(np.mean(late)),
                "eval_return": float(np.mean(evals)),
                "wall_s": round(wall, 1),
            }
            rows.append(row)
            print(
                f"[pairs] {algo} {name}: {row['train_return_first_quarter']:.1f} -> "
                f"{row['train_return_last_quarter']:.1f}, eval {row['eval_return']:.1f}",
                flush=True,
            )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))
    print(f"\npointmass, {steps} env steps, seeds {','.join(map(str, seeds))}\n")
    print("| explore | algo | train return, first -> last quarter | eval return | refused because |")
    print("|---|---|---|---|---|")
    for r in rows:
        if "refused" in r:
            reason = r["refused"].split("(allowed:", 1)[-1].rstrip(")").strip()
            print(f"| {r['explore']} | {r['algo']} | | | {reason} |")
        else:
            a, b, e = r["train_return_first_quarter"], r["train_return_last_quarter"], r["eval_return"]
            fmt = lambda v: "n/a" if math.isnan(v) else f"{v:.1f}"  # noqa: E731
            print(f"| {r['explore']} | {r['algo']} | {fmt(a)} -> {fmt(b)} | {fmt(e)} | |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
