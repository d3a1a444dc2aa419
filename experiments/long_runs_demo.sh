#!/usr/bin/env bash
# The sample of `coherent_jax.plot` in docs/runs.md: PPO on pointmass with action noise and
# with coherent exploration, SEEDS seeds each, then the learning-curve plot.
# Usage: experiments/long_runs_demo.sh [STEPS=32768] [SEEDS=3] [OUT=runs/demo-pointmass]
set -euo pipefail
STEPS=${1:-32768}
SEEDS=${2:-3}
OUT=${3:-runs/demo-pointmass}
for explore in action coherent; do
  for seed in $(seq 0 $((SEEDS - 1))); do
    python -m coherent_jax.train env=pointmass algo=ppo explore="$explore" seed="$seed" \
      total_steps="$STEPS" episode_length=100 num_envs=32 unroll_length=32 num_minibatches=4 eval_every=2 \
      eval_episodes=16 \
      progress=false run_dir="$OUT/$explore-s$seed"
  done
done
python -m coherent_jax.plot "$OUT" out="$OUT/plots"
