"""Gymnasium envs (``env=gym:ID``, a user's ``gymnasium.Env``) stepped on the host: the returns
are those of the env stepped by hand, refusals are one line with nothing written, the pool's
state survives a snapshot bit for bit, and a user's env is learned from the command line."""

import json
import os
import signal
import subprocess
import sys
import time

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROOT, child_env

from coherent_jax.config import ConfigError, parse_overrides
from coherent_jax.envs.host_gym import env_seeds
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.run.rundir import read_metrics

EXAMPLE = "examples/train_gym_env.py:TargetLine"


def _rollout(env: VecEnv, key, actions):
    """Reset from `key` and step through `actions` [T, n, a] under one jit; outcomes stacked."""

    def run(key):
        state = env.reset(key)

        def body(s, a):
            s, out = env.step(s, a)
            return s, out

        return jax.lax.scan(body, state, actions)

    return jax.jit(run)(key)


def test_pendulum_returns_equal_the_env_stepped_by_hand_across_autoresets():
    n, length, steps = 3, 40, 130  # three episodes and a part per env
    env = VecEnv("gym:Pendulum-v1", n, episode_length=length)
    assert (env.physics, env.observation_size, env.action_size, env.dt) == ("gym", 3, 1, 0.05)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, n, 1), minval=-1.5, maxval=1.5)
    key = jax.random.PRNGKey(7)
    _, out = _rollout(env, key, actions)
    # The seeds VecEnv.reset draws: its reset key split over the envs (vec_env.VecEnv.reset).
    seeds = np.asarray(env_seeds(jax.random.split(jax.random.split(key)[1], n)))
    clipped = np.clip(np.asarray(actions), -1.0, 1.0)
    for i in range(n):
        by_hand = gymnasium.make("Pendulum-v1", max_episode_steps=length)
        obs, _ = by_hand.reset(seed=int(seeds[i]))
        returns, ret, ends = [], np.float32(0), []
        for t in range(steps):
            obs, r, term, trunc, _ = by_hand.step(np.float32(2.0) * clipped[t, i].astype(np.float32))
            ret = np.float32(ret + np.float32(r))
            assert np.asarray(out.final_obs)[t, i] == pytest.approx(obs.astype(np.float32), abs=0)
            if term or trunc:
                returns.append(ret)
                ends.append(t)
                ret = np.float32(0)
                obs, _ = by_hand.reset()
        done = np.asarray(out.done)[:, i]
        assert np.flatnonzero(done).tolist() == ends == [39, 79, 119]
        assert np.asarray(out.truncated)[:, i].tolist() == done.tolist()  # Pendulum never terminates
        np.testing.assert_array_equal(np.asarray(out.episode_return)[done, i], np.array(returns, np.float32))


# (definition, words of the one-line refusal)
BAD = [
    ("gym:CartPole-v1", "action space is Discrete (allowed: a flat Box)"),
    ("gym:No-Such-Env-v0", "'No-Such-Env-v0' is not a registered Gymnasium id"),
    ("bad_gym_envs:DictObs", "observation space is Dict (allowed: a flat Box)"),
    ("bad_gym_envs:TupleAct", "action space is Tuple (allowed: a flat Box)"),
    ("bad_gym_envs:ImageObs", "observation space has shape (4, 4)"),
    ("bad_gym_envs:Unbounded", "action bounds [[-inf], [inf]] are not finite"),
    ("bad_gym_envs:ResetFails", "reset(seed=0) raised ValueError: the reset is broken"),
    ("bad_gym_envs:StepFails", "step(sample action) raised KeyError: 'no such joint'"),
    ("bad_gym_envs:not_annotated", "annotated '-> gymnasium.Env'"),
    ("bad_gym_envs:NanReset", "reset returned an observation with NaN at entry [1] (allowed: finite"),
    ("bad_gym_envs:InfStep", "step returned an observation with NaN at entry [1] and -inf at entry [0]"),
]


@pytest.mark.parametrize("name,problem", BAD, ids=[b[0].split(":")[-1] for b in BAD])
def test_refused_env_is_named_with_its_problem(name, problem, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "tests"))
    with pytest.raises(ConfigError) as err:
        parse_overrides([f"env={name}"])
    message = str(err.value)
    assert "\n" not in message and name in message and problem in message, message


def _cli(args, cwd, timeout=900, extra=None):
    env = {**child_env(), **(extra or {})}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "tests"), env["PYTHONPATH"]])
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=timeout
    )


@pytest.mark.parametrize("name", ["gym:CartPole-v1", "bad_gym_envs:StepFails"])
def test_refusal_from_the_command_line_exits_2_writing_nothing(tmp_path, name):
    proc = _cli(["-m", "coherent_jax.train", f"env={name}", f"run_dir={tmp_path / 'run'}"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and name in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "name,length",
    [
        ("gym:bad_gym_envs:BadGymEnvsGood-v0", 30),
        ("bad_gym_envs:good_factory", 1000),
        ("bad_gym_envs:Good", 1000),
    ],
)
def test_registering_module_factory_and_class_are_taken(name, length, monkeypatch):
    """``gym:MODULE:ID`` imports MODULE for its registration (episode length: the registered one);
    an annotated factory and a class are called; none of them is an MJCF task."""
    monkeypatch.syspath_prepend(str(ROOT / "tests"))
    cfg = parse_overrides([f"env={name}"])
    assert cfg.episode_length == length or cfg.episode_length == 0
    env = VecEnv(name, 2)
    assert (env.physics, env.observation_size, env.action_size, env.episode_length) == ("gym", 2, 1, length)


def test_episode_length_outlasts_the_registered_limit_but_not_a_limit_the_env_wears(monkeypatch):
    """``gym:ID`` is built without its registered TimeLimit, so ``episode_length`` above it is
    honoured (30 registered, 45 asked: the first truncation at step 45); an env whose own
    builder wraps that TimeLimit cannot run longer and is refused in one line."""
    monkeypatch.syspath_prepend(str(ROOT / "tests"))
    env = VecEnv("gym:bad_gym_envs:BadGymEnvsGood-v0", 1, episode_length=45)
    _, out = _rollout(env, jax.random.PRNGKey(0), jnp.zeros((50, 1, env.action_size)))
    assert np.flatnonzero(np.asarray(out.truncated)[:, 0]).tolist() == [44]
    assert parse_overrides(["env=bad_gym_envs:limited_factory"]).episode_length == 30
    with pytest.raises(ConfigError) as err:
        parse_overrides(["env=bad_gym_envs:limited_factory", "episode_length=45"])
    message = str(err.value)
    assert "\n" not in message and "'episode_length': 45" in message and "at most 30" in message, message


def test_physics_mjx_is_refused_for_a_gymnasium_env():
    with pytest.raises(ConfigError, match="Gymnasium envs step on the host"):
        parse_overrides(["env=gym:Pendulum-v1", "physics=mjx"])


def test_halfcheetah_pool_snapshot_resumes_bit_for_bit():
    """A pool restored from its snapshot steps on exactly as the original (MuJoCo state, the
    generator of later resets and the time limit's count all carried)."""
    n, length = 2, 7  # resets inside the second half
    env = VecEnv("gym:HalfCheetah-v5", n, episode_length=length)
    pool = env.env.pool
    actions = np.random.default_rng(0).uniform(-1, 1, (20, n, 6)).astype(np.float32)
    pool.reset(np.array([3, 4]))
    for t in range(5):
        pool.step(actions[t], np.full(n, t))
    blob = pool.snapshot()
    first = [pool.step(actions[t], np.full(n, t)) for t in range(5, 20)]
    pool.restore(blob)
    again = [pool.step(actions[t], np.full(n, t)) for t in range(5, 20)]
    for a, b in zip(first, again, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    with pytest.raises(RuntimeError, match="out of step"):
        pool.step(actions[0], np.full(n, 3))


def test_sweep_over_seeds_shares_one_pool_with_a_row_per_point():
    env = VecEnv("gym:Pendulum-v1", 2, episode_length=10)
    actions = jnp.zeros((12, 2, 1))
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    _, swept = jax.jit(jax.vmap(lambda k: _rollout(env, k, actions)))(keys)
    assert len(env.env.pool.envs) == 6
    for p in range(3):
        _, alone = _rollout(VecEnv("gym:Pendulum-v1", 2, episode_length=10), keys[p], actions)
        np.testing.assert_array_equal(np.asarray(swept.reward)[p], np.asarray(alone.reward))


@pytest.mark.slow
def test_user_env_is_learned_from_the_command_line(tmp_path):
    """The example's 1-D target reaching: a policy that does not move returns -33, the optimum -3.0."""
    run = tmp_path / "run"
    args = [f"env={ROOT / EXAMPLE.split(':')[0]}:TargetLine", "episode_length=50", "total_steps=100000"]
    proc = _cli(["-m", "coherent_jax.train", *args, "num_envs=16", f"run_dir={run}"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["final_eval_return"] > -8.0, summary


@pytest.mark.slow
def test_sigkill_then_resume_equals_an_uninterrupted_run(tmp_path):
    common = [
        "env=gym:Pendulum-v1",
        "num_envs=8",
        "total_steps=20480",
        "checkpoint_every=2",
        "progress=false",
    ]
    whole = _cli(["-m", "coherent_jax.train", *common, f"run_dir={tmp_path / 'whole'}"], tmp_path)
    assert whole.returncode == 0, whole.stderr
    env = child_env()
    cut = subprocess.Popen(
        [sys.executable, "-m", "coherent_jax.train", *common, f"run_dir={tmp_path / 'cut'}"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    while cut.poll() is None and not (tmp_path / "cut" / "checkpoint.msgpack").exists():
        time.sleep(0.05)
    cut.send_signal(signal.SIGKILL)
    assert cut.wait() == -signal.SIGKILL  # killed, not finished
    assert not (tmp_path / "cut" / "summary.json").exists()
    resumed = _cli(["-m", "coherent_jax.train", f"resume={tmp_path / 'cut'}"], tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert (tmp_path / "whole" / "params.msgpack").read_bytes() == (
        tmp_path / "cut" / "params.msgpack"
    ).read_bytes()

    def rows(run):
        lines = (tmp_path / run / "metrics.jsonl").read_text().splitlines()
        return [
            {k: v for k, v in json.loads(x).items() if not k.endswith("_s") and "per_s" not in k}
            for x in lines
        ]

    whole_rows, cut_rows = rows("whole"), rows("cut")
    assert len(whole_rows) == 40 and whole_rows == cut_rows


def test_a_gymnasium_env_runs_on_one_device_of_several(tmp_path):
    """Its copies step in one host pool: num_devices=2 is refused in one line before anything
    is written (it used to deadlock in a cross-device all-gather), and the default
    num_devices=0 ("all") means one device for it, all of them for an in-jit task."""
    env = child_env()
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "coherent_jax.train", "env=gym:Pendulum-v1", "num_devices=2"]
    r = subprocess.run([*cmd, f"run_dir={run_dir}"], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "'num_devices': 2" in lines[0] and "allowed: 1" in lines[0], r.stderr
    assert not run_dir.exists()
    probe = (
        "import jax; from coherent_jax.run.devices import resolve_num_devices as n; "
        "print(jax.device_count(), n(0, 'gym:Pendulum-v1'), n(0, 'pointmass'), n(0))"
    )
    r = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=300)
    assert r.stdout.split() == ["2", "1", "2", "2"], r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("command", ["coherent_jax.train", "coherent_jax.sweep"])
def test_an_env_that_raises_mid_run_stops_in_one_line_and_resumes_once_fixed(tmp_path, command):
    """A Gymnasium env whose ``step`` raises at iteration 3 (2 envs x 8 steps an iteration, one
    step at the check before; in a sweep both points share one pool): one line naming the
    iteration, the env and its error, exit status 1, the rows and the checkpoint of iteration 2
    kept; unset the fault and ``resume=`` runs to the end."""
    run = tmp_path / "run"
    args = ["env=bad_gym_envs:BreaksLater", "num_envs=2", "unroll_length=8", "ppo.num_minibatches=1",
            "total_steps=80", "episode_length=20", "eval_every=0", "eval_episodes=1", "checkpoint_every=1",
            "policy_hidden=[8]", "value_hidden=[8]", "progress=false", "tensorboard=false"]  # fmt: skip
    sweep = command.endswith("sweep")
    args += ["seeds=2"] if sweep else []
    # Step calls: 1 at the check, then 16 an iteration (32 in a sweep of 2 points): iteration 3's first.
    at = 66 if sweep else 34
    broken = _cli(["-m", command, *args, f"run_dir={run}"], tmp_path, extra={"BAD_GYM_BREAK_AT": str(at)})
    assert broken.returncode == 1, broken.stderr
    lines = broken.stderr.strip().splitlines()
    assert len(lines) == 1, broken.stderr
    assert lines[0].startswith(
        "error: at iteration 3, bad_gym_envs:BreaksLater raised in step() of env 0 "
    ), lines
    assert f"RuntimeError: the joint broke at call {at}" in lines[0] and f"resume={run}" in lines[0], lines
    assert "the checkpoint of iteration 2 is kept" in lines[0], lines
    logs = sorted(run.glob("*/metrics.jsonl")) if sweep else [run / "metrics.jsonl"]
    assert len(logs) == (2 if sweep else 1) and all(len(read_metrics(p)) == 2 for p in logs)
    fixed = _cli(["-m", command, f"resume={run}"], tmp_path)
    assert fixed.returncode == 0, fixed.stderr
    assert all(len(read_metrics(p)) == 5 for p in logs)
