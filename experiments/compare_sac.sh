#!/usr/bin/env bash
# SAC vs Coherent-SAC (thesis §4.3, §4.4.3), several seeds, SAC's defaults otherwise.
# usage: experiments/compare_sac.sh [ENV] [STEPS] [SEEDS] [BETA]
set -euo pipefail
env=${1:-halfcheetah}
steps=${2:-300000}
seeds=${3:-3}
beta=${4:-0.01}
out=runs/compare-sac-$env
for explore in action coherent; do
  for seed in $(seq 0 $((seeds - 1))); do
    python -m coherent_jax.train env="$env" algo=sac explore="$explore" beta="$beta" seed="$seed" \
      total_steps="$steps" progress=false run_dir="$out/sac-$explore-s$seed"
  done
done
python - "$out" <<'PY'
import json, pathlib, sys
for d in sorted(pathlib.Path(sys.argv[1]).iterdir()):
    s = json.loads((d / "summary.json").read_text())
    print(f"{d.name:28s} eval return {s['final_eval_return']:9.1f}  {s['train_env_steps_per_s']:8.0f} steps/s")
PY
