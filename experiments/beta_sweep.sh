#!/usr/bin/env bash
# Coherent-PPO over beta: trajectory-based (0) ... step-based (1).
# usage: experiments/beta_sweep.sh [ENV] [STEPS] [SEED]
set -euo pipefail
env=${1:-halfcheetah}
steps=${2:-2000000}
seed=${3:-0}
for beta in 0 0.01 0.1 1; do
  python -m coherent_jax.train env="$env" explore=coherent beta="$beta" seed="$seed" \
    total_steps="$steps" progress=false run_dir="runs/beta-$env/beta$beta-s$seed"
done
