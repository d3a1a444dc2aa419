"""A shipped policy of a Gymnasium env (``env=gym:ID``, a user's ``gymnasium.Env``): its actions
are in the env's own Box through the map training stepped the host pool with, in `predict`
and in the ONNX export, and `predict` in a hand-written Gymnasium loop returns what
``python -m coherent_jax.evaluate`` reports."""

import contextlib
import importlib.util
import io
import json

import gymnasium
import jax
import numpy as np
import onnxruntime
import pytest

import coherent_jax
from coherent_jax.config import make_config
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.host_gym import env_seeds
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.evaluate import main as evaluate_main
from coherent_jax.export import main as export_main
from coherent_jax.policy import hub, load_policy

LENGTH = 50
TINY = {
    "env": "gym:Pendulum-v1",
    "num_envs": 4,
    "unroll_length": 8,
    "episode_length": LENGTH,
    "total_steps": 64,  # two iterations
    "eval_every": 100,
    "eval_episodes": 2,
    "policy_hidden": [8],
    "value_hidden": [8],
    "ppo": {"num_epochs": 1, "num_minibatches": 1},
    "progress": False,
    "tensorboard": False,
}


@pytest.fixture(scope="module")
def pendulum_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("gym_policy") / "pendulum"
    coherent_jax.learn(make_config({**TINY, "run_dir": str(run_dir)}))
    return run_dir


def test_pendulum_predict_is_twice_the_clipped_mean_in_the_envs_box(pendulum_run, tmp_path):
    policy = load_policy(pendulum_run)
    box = gymnasium.make("Pendulum-v1").action_space
    assert policy.action_space == gymnasium.spaces.Box(box.low, box.high, dtype=np.float32)
    assert (policy.action_map.kind, policy.action_map.low.tolist(), policy.action_map.high.tolist()) == (
        "centre",
        [-2.0],
        [2.0],
    )
    obs = np.random.default_rng(0).normal(0, 3, (200, 3)).astype(np.float32)
    mean = np.asarray(policy.policy.mean_action(obs), np.float64)
    want = 2.0 * np.clip(mean, -1.0, 1.0)  # Pendulum's Box [-2, 2], computed apart from ActionMap
    got, _ = policy.predict(obs)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert np.abs(mean).max() > 1e-3  # the identity map (got == mean) would fail the check above
    # The ONNX export carries the same map.
    assert export_main([str(pendulum_run), "format=onnx", f"out={tmp_path / 'p.onnx'}"]) == 0
    session = onnxruntime.InferenceSession(str(tmp_path / "p.onnx"), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], got, rtol=0, atol=1e-5)


def test_predict_in_a_gymnasium_loop_returns_what_evaluate_reports(pendulum_run):
    episodes, seed = 3, 5
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert evaluate_main([str(pendulum_run), f"episodes={episodes}", f"seed={seed}"]) == 0
    reported = json.loads(out.getvalue().strip().splitlines()[-1])
    # The seeds evaluate's VecEnv.reset draws: its reset key split over the envs.
    key = jax.random.split(jax.random.PRNGKey(seed))[1]
    seeds = np.asarray(env_seeds(jax.random.split(key, episodes)))
    policy = load_policy(pendulum_run)
    returns = []
    for s in seeds:
        env = gymnasium.make("Pendulum-v1", max_episode_steps=LENGTH)
        obs, _ = env.reset(seed=int(s))
        ret, done, steps = np.float32(0), False, 0
        while not done:
            action, _ = policy.predict(obs.astype(np.float32))
            obs, reward, terminated, truncated, _ = env.step(action)
            ret, done, steps = np.float32(ret + np.float32(reward)), terminated or truncated, steps + 1
        assert steps == LENGTH
        returns.append(ret)
    returns = np.array(returns, np.float32)
    assert np.ptp(returns) > 0  # distinct episodes
    assert reported["episodes"] == episodes and reported["episode_length_mean"] == LENGTH
    assert (reported["engine"], reported["physics"]) == ("gymnasium", "gym")  # what stepped it
    assert reported["return_mean"] == pytest.approx(float(returns.mean()), rel=1e-6)
    assert reported["return_std"] == pytest.approx(float(returns.std()), rel=1e-5)


def _export_hub(run_dir, out, *extra):
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = export_main([str(run_dir), "format=hub", f"out={out}", "episodes=2", *extra])
    return status, printed.getvalue().splitlines()


def test_hub_folder_of_a_gymnasium_env_skips_a_replay_it_cannot_render(pendulum_run, tmp_path):
    """Pendulum-v1 renders through pygame: without it the folder has no replay and one line says
    why (docs/deploy.md: "where the task renders"); with it, the replay is there. A retry with
    force=true replaces the folder."""
    out = tmp_path / "hub"
    status, lines = _export_hub(pendulum_run, out)
    assert status == 0, lines
    renders = importlib.util.find_spec("pygame") is not None
    notes = [line for line in lines if "no replay video" in line]
    if renders:
        assert not notes and any(p.name.startswith("replay.") for p in out.iterdir())
    else:
        assert len(notes) == 1 and "render() raised DependencyNotInstalled" in notes[0], lines
        assert not any(p.name.startswith("replay.") for p in out.iterdir())
    assert {"README.md", "config.yaml", "policy.msgpack", "policy.json", "policy.onnx"} <= {
        p.name for p in out.iterdir()
    }
    assert load_policy(out).action_map.high.tolist() == [2.0]
    assert _export_hub(pendulum_run, out, "force=true")[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hub"]  # no partial sibling left


def test_a_failed_hub_export_leaves_no_folder(pendulum_run, tmp_path, monkeypatch):
    def fail(policy, path):
        raise ValueError("the ONNX writer broke")

    monkeypatch.setattr(hub, "write_onnx", fail)
    out = tmp_path / "new" / "hub"
    status, _ = _export_hub(pendulum_run, out)
    assert status == 2  # a ValueError: one line, exit 2
    assert list(tmp_path.iterdir()) == []  # neither the folder nor the parent it made
    (tmp_path / "old").mkdir()
    assert _export_hub(pendulum_run, tmp_path / "old" / "hub")[0] == 2
    assert [p.name for p in tmp_path.rglob("*")] == ["old"]  # an existing parent stays, empty
    monkeypatch.undo()
    assert _export_hub(pendulum_run, out)[0] == 0  # the retry is not blocked


def test_user_gymnasium_env_policy_maps_onto_its_own_box():
    env = VecEnv("bad_gym_envs:Skewed", 1, episode_length=10)
    amap = ActionMap.of_physics(env.env, env.action_size)  # what load_policy reads
    assert (amap.kind, amap.low.tolist(), amap.high.tolist()) == ("centre", [-3.0, 0.0], [1.0, 0.5])
    a = np.array([[-1.0, 1.0], [0.5, -0.5], [2.0, -7.0]], np.float32)
    want = np.array([[-3.0, 0.5], [0.0, 0.125], [1.0, 0.0]])  # low + (a + 1) (high - low) / 2, a clipped
    np.testing.assert_allclose(np.asarray(amap(a)), want, rtol=1e-6)
