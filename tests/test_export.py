"""Export (`coherent_jax.policy.formats`, ``python -m coherent_jax.export``): onnxruntime and
StableHLO against ``predict(deterministic=True)`` for every strategy of PPO and SAC, on policies
with random parameters and observation statistics (no training needed to compare graphs), a
non-unit action map; and the command's refusals of bad input."""

from __future__ import annotations

import subprocess
import sys

import jax
import numpy as np
import onnxruntime
import pytest
from helpers import child_env

from coherent_jax.config import make_config
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.networks import RunningStats
from coherent_jax.policy import Policy
from coherent_jax.policy.formats import run_stablehlo, write_onnx, write_stablehlo
from coherent_jax.policy.net import PolicyNet, policy_template
from coherent_jax.policy.onnx_graph import to_onnx
from coherent_jax.strategies import EXPLORES, SUPPORTED_ALGOS

OBS, ACT = 5, 3
CASES = [
    (algo, explore, extra)
    for explore in EXPLORES
    for algo in ("ppo", "sac")
    if algo in SUPPORTED_ALGOS[explore]
    for extra in (
        [{}, {"coherent.layers": "all", "coherent.integration": "mc"}]
        if (explore, algo) == ("coherent", "ppo")
        else [{}]
    )
]


def random_policy(
    algo: str, explore: str, extra: dict, seed: int = 0, env: str = "pointmass", sizes=(OBS, ACT), amap=None
) -> Policy:
    """A policy of task ``env`` with random parameters and observation statistics (no training)."""
    obs_size, action_size = sizes
    cfg = make_config({"env": env, "algo": algo, "explore": explore, "policy_hidden": [16, 8], **extra})
    template = policy_template(cfg, obs_size, action_size)["params"]
    leaves, tree = jax.tree.flatten(template)
    rng = np.random.default_rng(seed)
    params = jax.tree.unflatten(tree, [rng.normal(0, 0.7, t.shape).astype(t.dtype) for t in leaves])
    stats = RunningStats(
        mean=rng.normal(size=obs_size).astype(np.float32),
        var=rng.uniform(0.2, 3.0, obs_size).astype(np.float32),
        count=np.float32(100),
    )
    if amap is None:  # non-unit, one asymmetric
        amap = ActionMap.make("centre", [-3.0, -0.4, 0.0], [3.0, 0.4, 2.0])
    return Policy(PolicyNet.create(cfg, params, stats, obs_size, action_size), amap, {"source": "test"})


OBS_1000 = np.random.default_rng(1).normal(0, 2, (1000, OBS)).astype(np.float32)


@pytest.mark.parametrize(("algo", "explore", "extra"), CASES, ids=lambda v: str(v))
def test_onnx_equals_jax_for_every_strategy(algo, explore, extra, tmp_path):
    policy = random_policy(algo, explore, extra)
    write_onnx(policy, tmp_path / "p.onnx")
    session = onnxruntime.InferenceSession(str(tmp_path / "p.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(["action"], {"obs": OBS_1000})[0]
    want, _ = policy.predict(OBS_1000, deterministic=True)
    assert got.shape == (1000, ACT) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    assert np.ptp(want, axis=0).min() > 0.05  # the actions vary: the comparison means something
    assert np.all(want >= policy.action_map.low) and np.all(want <= policy.action_map.high)
    assert session.run(["action"], {"obs": OBS_1000[:1]})[0].shape == (1, ACT)  # any batch size


def test_stablehlo_equals_jax(tmp_path):
    policy = random_policy("sac", "lattice", {})
    write_stablehlo(policy, tmp_path / "p.stablehlo")
    got = run_stablehlo((tmp_path / "p.stablehlo").read_bytes(), OBS_1000)
    np.testing.assert_allclose(got, policy.predict(OBS_1000)[0], rtol=0, atol=1e-6)
    got7 = run_stablehlo((tmp_path / "p.stablehlo").read_bytes(), OBS_1000[:7])  # symbolic batch
    np.testing.assert_allclose(got7, got[:7], rtol=0, atol=1e-6)


def test_onnx_runs_without_jax_or_this_package(tmp_path):
    write_onnx(random_policy("ppo", "coherent", {}), tmp_path / "p.onnx")
    code = (
        "import sys, numpy as np, onnxruntime as ort; "
        f"s = ort.InferenceSession({str(tmp_path / 'p.onnx')!r}); "
        f"a = s.run(None, {{'obs': np.zeros((4, {OBS}), np.float32)}})[0]; "
        "assert 'jax' not in sys.modules and 'coherent_jax' not in sys.modules; print(a.shape)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "(4, 3)", out.stderr


def test_unknown_primitive_is_refused_by_name():
    from coherent_jax.policy.onnx_graph import ExportError

    with pytest.raises(ExportError, match="unsupported primitive 'sin'"):
        to_onnx(lambda o: jax.numpy.sin(o), 2, 2)


def _export(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.export", *args],
        env=child_env(),
        capture_output=True,
        text=True,
        cwd=cwd,
    )


def test_bad_input_one_line_exit_2_nothing_written(tmp_path):
    out = _export(str(tmp_path / "missing"), "format=onnx", cwd=tmp_path)
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
    assert "not a directory (allowed: a run directory)" in out.stderr
    run = tmp_path / "run"
    run.mkdir()
    out = _export(str(run), "format=tflite", cwd=tmp_path)
    assert out.returncode == 2 and out.stderr.count("\n") == 1
    assert "invalid value for 'format': 'tflite' (allowed: onnx or stablehlo or hub)" in out.stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["run"]
