"""The Python API: coherent_jax.learn(config), coherent_jax.load_policy(run_dir), make_config."""

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml
from helpers import child_env

import coherent_jax
from coherent_jax.config import ConfigError, make_config, parse_overrides, to_dict

TINY = {
    "env": "pointmass",
    "num_envs": 8,
    "unroll_length": 16,
    "episode_length": 40,
    "total_steps": 384,  # 3 iterations
    "eval_every": 2,
    "eval_episodes": 4,
    "policy_hidden": [16, 16],
    "value_hidden": [16, 16],
    "ppo": {"num_epochs": 2, "num_minibatches": 2},
    "progress": False,
    "tensorboard": False,
}


def test_import_is_cheap_and_the_api_is_lazy():
    """``import coherent_jax`` and its Config load no JAX; train and load_policy are the API's."""
    code = (
        "import sys, coherent_jax; assert 'jax' not in sys.modules; "
        "coherent_jax.make_config(env='pointmass'); assert 'jax' not in sys.modules; "
        "import coherent_jax.api as api; from coherent_jax.train import main; "
        "assert coherent_jax.learn is api.learn and coherent_jax.load_policy is api.load_policy; print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_make_config_layers_like_the_command_line():
    cfg = make_config(env="hopper", preset="thesis", **{"ppo.clip_eps": 0.1})
    assert cfg == parse_overrides(["env=hopper", "preset=thesis", "ppo.clip_eps=0.1"])
    assert cfg.ppo.num_epochs == 80 and cfg.ppo.clip_eps == 0.1 and cfg.num_envs == 4  # preset, then user
    nested = make_config({"env": "hopper", "preset": "thesis", "ppo": {"clip_eps": 0.1}})
    assert nested == cfg
    sac = make_config({"algo": "sac", "num_envs": 2}, lr=1e-5)  # keywords win over the mapping
    assert sac.policy_hidden == [256, 256] and sac.num_envs == 2 and sac.lr == 1e-5
    # A string YAML would read otherwise stays a string; a Config's items rebuild it exactly.
    odd = make_config(run_dir="runs/true, or not", lr=3.0e-4 / 7)
    assert odd.run_dir == "runs/true, or not"
    assert make_config(to_dict(odd)) == odd


@pytest.mark.parametrize(
    "config, message",
    [
        ({"ppo.clip": 0.2}, r"^unknown key 'ppo\.clip' \(did you mean ppo\.clip_eps\?\); valid keys: --help"),
        ({"lr": "fast"}, r"^invalid value for 'lr': .*\(allowed: a number\)$"),
        ({"lr": -1.0}, r"^invalid value for 'lr': -1\.0"),
        ({"env": "mars"}, r"^invalid value for 'env': .*pointmass"),
        (
            {"lr": object()},
            r"^invalid value for 'lr': .*\(allowed: a bool, number, string, path, list or None\)$",
        ),
        (["env=pointmass"], r"^invalid config .*a list \(allowed: a coherent_jax\.Config or a mapping"),
        ({"distributed": True}, r"^invalid value for 'distributed': True in coherent_jax\.learn"),
    ],
)
def test_bad_config_raises_one_line_and_writes_nothing(tmp_path, config, message):
    if isinstance(config, dict):
        config = {**config, "run_dir": str(tmp_path / "run")}
    with pytest.raises(ConfigError, match=message) as info:
        coherent_jax.learn(config)
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


def _episodes_with(fn, run_dir, episodes, seed):
    """Returns of `episodes` deterministic episodes stepped from Python with ``fn`` (numpy obs ->
    numpy action), from the reset evaluation makes with the same key (`rollout.evaluate_policy`)."""
    import jax

    from coherent_jax.envs.vec_env import VecEnv
    from coherent_jax.run.checkpoint import load_config

    cfg = load_config(run_dir)
    env = VecEnv(cfg.env, episodes, cfg.episode_length, cfg.physics, cfg.physics_threads)
    state, step = env.reset(jax.random.PRNGKey(seed)), jax.jit(env.step)
    returns, running = np.zeros(episodes), np.ones(episodes, bool)
    for _ in range(env.episode_length):
        state, outcome = step(state, fn(np.asarray(state.obs)))
        returns += np.where(running, np.asarray(outcome.reward), 0.0)
        running &= ~np.asarray(outcome.done)
    return returns


@pytest.mark.slow
def test_train_returns_the_run_and_its_policy_acts_as_evaluation_does(tmp_path):
    """A tiny run through the API: the result's fields hold what the run wrote; its policy is
    the one ``python -m coherent_jax.evaluate`` evaluates, action for action."""
    from coherent_jax.evaluate import EvalConfig
    from coherent_jax.policy.net import read_policy
    from coherent_jax.run.evaluation import evaluate_run
    from coherent_jax.run.rundir import read_metrics
    from coherent_jax.train import main

    cfg = make_config({**TINY, "seed": 5, "run_dir": str(tmp_path / "api")})
    result = coherent_jax.learn(cfg)
    assert isinstance(result, coherent_jax.TrainResult)
    assert result.run_dir == tmp_path / "api"
    assert result.metrics == read_metrics(result.run_dir / "metrics.jsonl")
    assert [r["iteration"] for r in result.metrics] == [1, 2, 3]
    assert "eval/episode_return" in result.metrics[1] and "eval/episode_return" not in result.metrics[0]
    assert result.summary == json.loads((result.run_dir / "summary.json").read_text())
    assert result.summary["final_eval_return"] == result.metrics[-1]["eval/episode_return"]
    assert yaml.safe_load((result.run_dir / "config.yaml").read_text()) == {**to_dict(cfg), "resume": ""}

    # The command line runs the same function: the same rows.
    assert main([f"{k}={v}" for k, v in _flat(TINY).items()] + ["seed=5", f"run_dir={tmp_path / 'cli'}"]) == 0
    cli_rows = read_metrics(tmp_path / "cli" / "metrics.jsonl")
    assert _no_times(cli_rows) == _no_times(result.metrics)

    # The policy: numpy in, numpy out, the evaluation's mean action (clipped as the env clips).
    policy = coherent_jax.load_policy(result.run_dir)
    obs = np.random.default_rng(0).normal(size=(16, 6)).astype(np.float32) * 3
    actions = policy(obs)
    assert isinstance(actions, np.ndarray) and actions.shape == (16, 2) and actions.dtype == np.float32
    inner, _ = read_policy(result.run_dir, 6, 2)
    np.testing.assert_allclose(actions, np.clip(np.asarray(inner.mean_action(obs)), -1, 1), rtol=1e-6)
    np.testing.assert_allclose(policy(obs[3]), actions[3], rtol=1e-6)  # one obs: another compile
    np.testing.assert_array_equal(result.policy(obs), actions)
    with pytest.raises(
        ValueError, match=r"^invalid observation of shape \[5\] \(allowed: \[6\] or \[n, 6\]\)$"
    ):
        policy(np.zeros(5))

    # Episodes stepped from Python with it return what evaluate reports for the same seed.
    opts = EvalConfig(
        episodes=4, engine="jax", video=False, seed=2, video_path="", width=16, height=16, max_frames=2
    )
    evaluated = evaluate_run(result.run_dir, opts)
    returns = _episodes_with(policy, result.run_dir, 4, seed=2)
    assert returns.mean() == pytest.approx(evaluated["return_mean"], rel=1e-4)
    assert returns.std() == pytest.approx(evaluated["return_std"], rel=1e-3, abs=1e-4)


def _flat(values, prefix=""):
    out = {}
    for k, v in values.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            shown = str(v).lower() if isinstance(v, bool) else str(v).replace(" ", "")
            out[f"{prefix}{k}"] = shown
    return out


def _no_times(rows):
    return [{k: v for k, v in r.items() if k != "time_s"} for r in rows]
