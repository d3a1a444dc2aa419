"""JAX environments with Brax's interface named ``env=MODULE:NAME`` (`coherent_jax.envs.jax_env`):
the path equals stepping the env by hand, across auto-resets; what is refused, in one line;
training from the command line and evaluation.

`Drift` is a tiny hand-written Brax env in pure JAX (no physics to compile): a point on a
line pushed by the action, paid -x^2, terminated once |x| > 1. The command-line tests
name it by this file's path.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import Env, State

from coherent_jax.config import parse_overrides
from coherent_jax.config.checks import ConfigError
from coherent_jax.envs import jax_env
from coherent_jax.envs.registry import PhysicsError, TaskDefinitionError, check_task, resolve_physics
from coherent_jax.envs.vec_env import VecEnv

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve()


class Drift(Env):
    """x' = x + 0.5 a, v = 0.5 a; obs (x, v); r = -x'^2; done when |x'| > 1; x0 ~ U(-0.5, 0.5)."""

    def reset(self, rng: jax.Array) -> State:
        x = jax.random.uniform(rng, (), minval=-0.5, maxval=0.5)
        obs = jnp.stack([x, jnp.zeros(())])
        return State(pipeline_state=None, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()))

    def step(self, state: State, action: jax.Array) -> State:
        v = 0.5 * action[0]
        x = state.obs[0] + v
        done = (jnp.abs(x) > 1.0).astype(jnp.float32)
        return state.replace(obs=jnp.stack([x, v]), reward=-jnp.square(x), done=done)

    @property
    def observation_size(self) -> int:
        return 2

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"


drift = Drift()


def make_drift() -> Drift:
    return Drift()


class DictDrift(Drift):
    def reset(self, rng: jax.Array) -> State:
        state = super().reset(rng)
        return state.replace(obs={"state": state.obs})

    def step(self, state: State, action: jax.Array) -> State:
        return state


class ImageDrift(Drift):
    def reset(self, rng: jax.Array) -> State:
        state = super().reset(rng)
        return state.replace(obs=jnp.zeros((4, 4)))


def broken_factory() -> Drift:
    raise RuntimeError("no such level")


def not_declared():  # returns an env but is not annotated to: never called
    raise AssertionError("called")


NAME = f"{HERE}:drift"


def test_the_attribute_is_recognised_without_calling_anything():
    assert jax_env.is_brax_env(drift) and jax_env.is_brax_env(Drift) and jax_env.is_brax_env(make_drift)
    assert not jax_env.is_brax_env(not_declared) and not jax_env.is_brax_env(os.system)
    assert not jax_env.is_brax_env(State) and not jax_env.is_brax_env(3)


@pytest.mark.parametrize("attr", ["drift", "Drift", "make_drift"])
def test_instance_class_and_factory_load_with_their_sizes(attr):
    spec = check_task(f"{HERE}:{attr}")
    assert spec.backend == jax_env.JAX_ENV_BACKEND and spec.episode_length == 1000
    assert "(2 obs, 1 act)" in spec.description
    env = VecEnv(f"{HERE}:{attr}", 3)
    assert (env.observation_size, env.action_size, env.physics) == (2, 1, "jax-env")


def test_the_path_equals_stepping_the_env_by_hand_across_auto_resets():
    """Three envs, a time limit of 5 and actions that push env 0 out of [-1, 1] (terminated)
    while env 2 is truncated: outcome and next observations equal the env's own reset and
    step under VecEnv's key schedule, one env at a time."""
    n, limit, steps = 3, 5, 12
    vec = VecEnv(NAME, n, episode_length=limit)
    actions = jnp.array([[1.0], [-0.3], [0.05]]) * jnp.ones((steps, n, 1))
    state = vec.reset(jax.random.PRNGKey(7))
    step = jax.jit(vec.step)
    got = []
    for t in range(steps):
        state, out = step(state, actions[t])
        got.append((out.final_obs, out.reward, out.terminated, out.truncated, state.obs))

    key, reset_key = jax.random.split(jax.random.PRNGKey(7))
    envs = [drift.reset(k) for k in jax.random.split(reset_key, n)]
    count = np.zeros(n, int)
    terminated_seen = truncated_seen = 0
    for t in range(steps):
        key, reset_key = jax.random.split(key)
        fresh = jax.random.split(reset_key, n)
        for i in range(n):
            after = drift.step(envs[i], actions[t, i])
            count[i] += 1
            terminated = bool(after.done > 0.5)
            truncated = count[i] >= limit and not terminated
            final_obs, reward, term, trunc, next_obs = (np.asarray(g[i]) for g in got[t])
            np.testing.assert_array_equal(final_obs, after.obs)
            np.testing.assert_array_equal(reward, after.reward)
            assert (bool(term), bool(trunc)) == (terminated, truncated), (t, i)
            if terminated or truncated:
                after, count[i] = drift.reset(fresh[i]), 0
            envs[i] = after
            np.testing.assert_array_equal(next_obs, after.obs)
            terminated_seen += terminated
            truncated_seen += truncated
    assert terminated_seen >= 3 and truncated_seen >= 2  # both kinds of episode end happened


@pytest.mark.parametrize(
    "attr, problem",
    [
        ("DictDrift", "observations are a dict (state) after a reset; allowed: one flat vector"),
        ("ImageDrift", "the observation after a reset has shape (4, 4) per env; allowed: a vector"),
        ("broken_factory", "broken_factory() raised RuntimeError: no such level"),
    ],
)
def test_bad_envs_are_refused_in_one_line(attr, problem):
    with pytest.raises(TaskDefinitionError) as info:
        check_task(f"{HERE}:{attr}")
    message = str(info.value)
    assert problem in message and attr in message and "\n" not in message


def test_a_function_not_declared_to_make_an_env_is_not_called():
    with pytest.raises(TaskDefinitionError, match="without the return annotation"):
        check_task(f"{HERE}:not_declared")


@pytest.mark.parametrize("physics", ["mjx", "native"])
def test_physics_other_than_auto_is_refused(physics):
    with pytest.raises(PhysicsError, match="allowed: auto"):
        resolve_physics(NAME, physics)
    with pytest.raises(ConfigError) as info:
        parse_overrides([f"env={NAME}", f"physics={physics}"])
    assert f"invalid value for 'physics': '{physics}'" in str(info.value) and "auto" in str(info.value)


def _cli(args, cwd):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests"), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=900
    )


def test_physics_mjx_from_the_command_line_exits_2_writing_nothing(tmp_path):
    proc = _cli(["-m", "coherent_jax.train", f"env={NAME}", "physics=mjx"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "physics" in lines[0] and "allowed: auto" in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_train_one_iteration_from_the_command_line_then_evaluate(tmp_path):
    run = tmp_path / "run"
    tiny = ["num_envs=8", "unroll_length=8", "total_steps=64", "policy_hidden=[8]", "value_hidden=[8]"]
    quiet = ["progress=false", "tensorboard=false", "eval_episodes=4"]
    proc = _cli(["-m", "coherent_jax.train", f"env={NAME}", *tiny, *quiet, f"run_dir={run}"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 1 and summary["physics"] == "jax-env"
    assert np.isfinite(summary["final_eval_return"]) and summary["final_eval_return"] <= 0.0  # r = -x^2

    proc = _cli(["-m", "coherent_jax.evaluate", str(run), "episodes=4"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert np.isfinite(result["return_mean"]) and result["return_mean"] <= 0.0

    proc = _cli(["-m", "coherent_jax.evaluate", str(run), "video=true"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "exposes no MuJoCo model" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_playground_env_steps_as_playground_steps_it_and_exposes_its_model():
    """The example's 3-link swimmer (MJX compiles: slow): two envs, three steps from the same
    keys and actions, by `VecEnv` and by the env itself; its model and positions for video."""
    name = f"{ROOT / 'examples' / 'train_playground_env.py'}:swimmer3"
    vec = VecEnv(name, 2)
    env = jax_env.jax_env(name)
    assert env.mj_model is not None and env.mj_model.nq == 5  # x, y, heading and two joints
    actions = jax.random.uniform(jax.random.PRNGKey(1), (3, 2, vec.action_size), minval=-1, maxval=1)

    # Scanned, so that XLA compiles one MJX step, not three.
    def by_vec(key):
        def step(state, action):
            state, out = vec.step(state, action)
            return state, (out.final_obs, out.reward)

        state, (obs, reward) = jax.lax.scan(step, vec.reset(key), actions)
        return obs[-1], reward[-1], env.qpos(state.physics)

    def by_hand(key):
        _, reset_key = jax.random.split(key)
        state = jax.vmap(env.env.reset)(jax.random.split(reset_key, 2))
        state = jax.lax.scan(lambda s, a: (jax.vmap(env.env.step)(s, a), None), state, actions)[0]
        return state.obs, state.reward, state.data.qpos

    key = jax.random.PRNGKey(5)
    options = {"xla_backend_optimization_level": 0}  # three steps: the compile is the cost
    got_all, want_all = (jax.jit(f).lower(key).compile(options)(key) for f in (by_vec, by_hand))
    for got, want in zip(got_all, want_all, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
