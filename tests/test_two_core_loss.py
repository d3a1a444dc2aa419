"""experiments/two_core_loss.py: the thesis buffer's loss split over two CPU devices.

The split losses (`jax.shard_map` and XLA's SPMD partitioner, envs split over two host
devices) must give the one-device loss's value and gradient to float32 rounding, and a
callback pinned to one device of a replicated two-device scan must still run once per
step; the script checks both and exits 1 if either fails.
"""

import json
import subprocess
import sys

import pytest
from helpers import ROOT, child_env

SCRIPT = str(ROOT / "experiments" / "two_core_loss.py")


def _run(*args):
    return subprocess.run(
        [sys.executable, SCRIPT, *args], capture_output=True, text=True, env=child_env(), timeout=300
    )


@pytest.mark.slow
def test_the_split_losses_equal_the_one_device_loss_and_the_pinned_callback_runs_once_a_step(tmp_path):
    out = tmp_path / "two_core.json"
    proc = _run(str(out), "--envs", "2", "--steps", "30", "--rounds", "1")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(out.read_text())
    assert set(result["loss_rel_err"]) == {"shard_map, 2 devices", "SPMD, 2 devices"}
    assert all(err < 1e-4 for err in result["loss_rel_err"].values())
    assert result["callbacks_per_rollout"] == {"one device": 30, "replicated, callback on device 0": 30}
    assert all(ms > 0 for ms in result["loss_ms"].values())


def test_an_odd_env_count_exits_2_naming_the_value_and_writes_nothing(tmp_path):
    out = tmp_path / "two_core.json"
    proc = _run(str(out), "--envs", "3")
    assert proc.returncode == 2
    assert "invalid value '3'" in proc.stderr and "even" in proc.stderr
    assert not out.exists()
