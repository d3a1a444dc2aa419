"""The SAC benchmark: bad settings refused up front; a tiny real run writes consistent figures."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from coherent_jax.bench_sac import format_sac_table, run_sac_bench
from coherent_jax.config import ConfigError


def run_cli(args, cwd):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.bench", "sac", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize(
    "args,key",
    [(["explore=coherent"], "'explore'"), (["iterations=0"], "'iterations'"), (["bogus=1"], "'bogus'")],
)
def test_bad_settings_exit_2_and_write_nothing(tmp_path, args, key):
    proc = run_cli([*args, f"out={tmp_path / 'r.json'}"], cwd=tmp_path)
    assert proc.returncode == 2
    assert key in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_tiny_run_reports_both_strategies(tmp_path):
    out = tmp_path / "sac.json"
    overrides = [
        "env=pointmass",
        "num_envs=4",
        "unroll_length=8",
        "policy_hidden=[16]",
        "value_hidden=[16]",
        "batch_size=16",
        "utd_ratio=0.25",
        "iterations=2",
        f"out={out}",
    ]
    result = run_sac_bench(overrides, log=lambda msg: None)
    saved = json.loads(out.read_text())
    tr = saved["training"]
    assert tr["env_steps_per_iteration"] == 32 and tr["updates_per_iteration"] == 8
    for name in ("action", "coherent"):
        e = tr[name]
        assert len(e["iteration_s"]) == 2 and e["compile_s"] > 0
        assert e["env_steps_per_s"] == pytest.approx(32 / e["iteration_s_median"])
        assert e["gradient_updates_per_s"] == pytest.approx(8 / e["iteration_s_median"])
    assert "Coherent-SAC / SAC" in format_sac_table(result)
    with pytest.raises(ConfigError):
        run_sac_bench(["algo=ppo"])
