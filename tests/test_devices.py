"""Two CPU devices: envs (train) and grid points (sweep) are really split, and results do not change.

JAX fixes its device count when it initialises, so the check runs in a fresh
interpreter with ``XLA_FLAGS=--xla_force_host_platform_device_count=2``.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import child_env

SCRIPT = r"""
import json, sys
from pathlib import Path

import jax
import numpy as np

from coherent_jax.run import devices, loop

from coherent_jax import sweep, train
from coherent_jax.agents import make_trainer
from coherent_jax.config import parse_overrides

tmp = Path(sys.argv[1])
TINY = ["env=pointmass", "num_envs=8", "unroll_length=8", "ppo.num_minibatches=2", "eval_episodes=2",
        "episode_length=50", "eval_every=0", "progress=false", "total_steps=128"]
cfg = parse_overrides(TINY)
out = {"device_count": jax.device_count()}
for n in (1, 2):
    trainer = make_trainer(cfg)
    _, init_key = loop.run_keys(cfg.seed)
    state, shardings = devices.init_state(trainer, init_key, n, cfg.num_envs)
    iteration = devices.compile_iteration(trainer, state, shardings)
    metrics = []
    for _ in range(cfg.num_iterations):
        state, m = iteration(state)
        metrics.append({k: float(v) for k, v in jax.device_get(m).items()})
    obs = state.env_state.obs
    out[str(n)] = {
        "metrics": metrics,
        "obs_devices": devices.device_count_of(obs),
        "obs_shard_rows": sorted(s.data.shape[0] for s in obs.addressable_shards),
        "physics_split": all(
            devices.device_count_of(x) == n and x.addressable_shards[0].data.shape[0] == 8 // n
            for x in jax.tree.leaves(state.env_state.physics)
        ),
        "params_replicated": all(
            x.sharding.is_fully_replicated for x in jax.tree.leaves((state.params, state.opt_state))
        ),
        "params": [np.asarray(x).ravel().tolist() for x in jax.tree.leaves(state.params)],
    }
split = [o for o in TINY if not o.startswith(("num_envs=", "ppo.num_minibatches="))]  # each key once
out["bad_split"] = train.main([*split, "num_envs=5", "ppo.num_minibatches=1", f"run_dir={tmp / 'bad1'}"])
out["too_many"] = train.main([*TINY, "num_devices=3", f"run_dir={tmp / 'bad2'}"])
out["sweep"] = sweep.main([*TINY, "seeds=2", f"run_dir={tmp / 'sweep'}"])
(tmp / "result.json").write_text(json.dumps(out))
"""


@pytest.mark.slow
def test_two_cpu_devices_split_envs_and_sweep_points(tmp_path):
    env = child_env()
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads((tmp_path / "result.json").read_text())
    assert out["device_count"] == 2

    one, two = out["1"], out["2"]
    # Really split: every per-env array lives half on each device; parameters are replicated.
    assert one["obs_devices"] == 1 and one["obs_shard_rows"] == [8]
    assert two["obs_devices"] == 2 and two["obs_shard_rows"] == [4, 4]
    assert two["physics_split"] and one["physics_split"]
    assert two["params_replicated"]
    # Same training: the 2-device gradient is the mean over all envs, as on one device.
    assert len(one["metrics"]) == len(two["metrics"]) == 2
    for m1, m2 in zip(one["metrics"], two["metrics"], strict=True):
        assert m1.keys() == m2.keys()
        for k in m1:
            assert m2[k] == pytest.approx(m1[k], rel=1e-4, abs=1e-5, nan_ok=True), k
    for p1, p2 in zip(one["params"], two["params"], strict=True):
        np.testing.assert_allclose(p2, p1, rtol=1e-4, atol=1e-5)

    # Bad device splits are refused in one line with status 2, before writing.
    assert out["bad_split"] == 2 and out["too_many"] == 2
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert any("'num_envs'" in ln and "2 devices" in ln for ln in errors), errors
    assert any("'num_devices'" in ln for ln in errors), errors
    assert not (tmp_path / "bad1").exists() and not (tmp_path / "bad2").exists()

    # The sweep put one point on each device; point 0 (seed 0) is the run above.
    assert out["sweep"] == 0
    result = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert result["num_devices"] == 2 and result["num_points"] == 2
    rows = [
        json.loads(x) for x in (tmp_path / "sweep" / "p000-seed=0" / "metrics.jsonl").read_text().splitlines()
    ]
    for row, ref in zip(rows, one["metrics"], strict=True):
        for k, v in ref.items():
            assert (row[k] if row[k] is not None else float("nan")) == pytest.approx(
                v, rel=1e-4, abs=1e-5, nan_ok=True
            ), k
