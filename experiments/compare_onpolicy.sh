#!/usr/bin/env bash
# PPO and A2C, action noise vs coherent exploration, several seeds.
# usage: experiments/compare_onpolicy.sh [ENV] [STEPS] [SEEDS]
set -euo pipefail
env=${1:-halfcheetah}
steps=${2:-2000000}
seeds=${3:-3}
out=runs/compare-$env
for algo in ppo a2c; do
  for explore in action coherent; do
    for seed in $(seq 0 $((seeds - 1))); do
      python -m coherent_jax.train env="$env" algo="$algo" explore="$explore" seed="$seed" \
        total_steps="$steps" progress=false run_dir="$out/$algo-$explore-s$seed"
    done
  done
done
python - "$out" <<'PY'
import json, pathlib, sys
for d in sorted(pathlib.Path(sys.argv[1]).iterdir()):
    s = json.loads((d / "summary.json").read_text())
    print(f"{d.name:28s} eval return {s['final_eval_return']:9.1f}  {s['train_env_steps_per_s']:8.0f} steps/s")
PY
