"""Native MuJoCo physics (``physics=native``): for Brax's re-creations the same task as MJX; under jit,
reproducible. Gymnasium's tasks are held to Gymnasium itself in ``test_gymnasium_tasks.py``."""

import os

import jax
import numpy as np
import pytest
from helpers import BRAX_SIZES, MJX_SIDE_BY_SIDE, native_and_mjx_rollouts

from coherent_jax.agents.onpolicy import OnPolicyTrainer
from coherent_jax.config import ConfigError, parse_overrides
from coherent_jax.envs import VecEnv, env_sizes, make_brax_env
from coherent_jax.envs.physics import NATIVE_TASKS, NativeState
from coherent_jax.envs.registry import PhysicsError, resolve_physics

# MJX programs take 10-60 s each to compile here: the suite checks two tasks;
# COHERENT_ALL_PHYSICS=1 checks every native Brax task the same way.
ALWAYS = MJX_SIDE_BY_SIDE
BRAX_NATIVE = [task for task in NATIVE_TASKS if task.startswith("brax-")]


# brax-halfcheetah's MJX program compiles in about 20 s: the full suite checks it, the everyday
# subset checks brax-inverted_pendulum.
@pytest.mark.parametrize(
    "task", [pytest.param(t, marks=pytest.mark.slow) if t == "brax-halfcheetah" else t for t in BRAX_NATIVE]
)
def test_native_steps_match_mjx_side_by_side(task):
    """From the same keys (so identical initial states) and actions, native MuJoCo and MJX give
    the same observations, rewards and terminations for several steps, to float32 accuracy.

    Both engines run MuJoCo's algorithms on the same model and solver settings; MJX in
    float32 and native in float64, so the trajectories agree to a relative 1e-3 over a
    few steps (they drift apart slowly through contacts, as any two float precisions do).
    """
    if task not in ALWAYS and not os.environ.get("COHERENT_ALL_PHYSICS"):
        pytest.skip("MJX compile is slow; set COHERENT_ALL_PHYSICS=1 to check every native task")
    steps = 5
    mjx, native = native_and_mjx_rollouts(task, 2, steps)
    (obs0_m, (obs_m, rew_m, done_m)), (obs0_n, (obs_n, rew_n, done_n)) = mjx, native
    # Same reset distribution (to float32 rounding: ant's quaternion is normalised in float64 here).
    np.testing.assert_allclose(np.asarray(obs0_n), np.asarray(obs0_m), rtol=1e-6, atol=1e-7)
    scale = 1.0 + np.abs(np.asarray(obs_m))
    assert np.max(np.abs(np.asarray(obs_n) - np.asarray(obs_m)) / scale) < 1e-3
    np.testing.assert_allclose(np.asarray(rew_n), np.asarray(rew_m), rtol=1e-3, atol=1e-3)
    np.testing.assert_array_equal(np.asarray(done_n), np.asarray(done_m))
    # What the registry's smoke test (test_envs.py) checks of the other Brax tasks.
    obs_size, act_size = BRAX_SIZES[task]
    assert env_sizes(make_brax_env(task)) == (obs_size, act_size)
    assert obs0_m.shape == (2, obs_size) and obs_m.shape == (steps, 2, obs_size) and rew_m.shape == (steps, 2)
    assert np.isfinite(np.asarray(obs_m)).all() and np.isfinite(np.asarray(rew_m)).all()
    # The comparison is not vacuous: the state moved and rewards vary.
    assert np.max(np.abs(np.asarray(obs_m[-1]) - np.asarray(obs0_m))) > 1e-2
    if task == "brax-inverted_pendulum":
        assert np.all(np.asarray(rew_n) == 1.0)
    else:
        assert np.std(np.asarray(rew_m)) > 1e-3


def test_native_env_is_pure_and_vmaps_over_seeds():
    """The state travels in JAX: the same key twice gives the same run, and a vmap over two
    seeds equals the two runs one by one (the callback receives both batches at once)."""
    env = VecEnv("inverted_pendulum", num_envs=3, episode_length=50, physics="native")
    assert env.physics == "native" and (env.observation_size, env.action_size) == (4, 1)

    def make_run(env):
        def run(key):
            state = env.reset(key)

            def body(s, k):
                s, out = env.step(s, jax.random.uniform(k, (3, 1), minval=-1, maxval=1))
                return s, (out.reward, out.final_obs, out.terminated)

            return jax.lax.scan(body, state, jax.random.split(key, 40))

        return run

    run = make_run(env)

    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    state, outs = jax.jit(jax.vmap(run))(keys)
    single = jax.jit(run)
    for i in range(2):
        state_i, outs_i = single(keys[i])
        for a, b in zip(jax.tree.leaves((state_i, outs_i)), jax.tree.leaves((state, outs)), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b[i]))
    again = single(keys[0])
    for a, b in zip(jax.tree.leaves(again), jax.tree.leaves(single(keys[0])), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert isinstance(state.physics, NativeState)
    assert np.asarray(outs[2]).any(), "pendulums fall under random actions, so auto-reset ran"
    # MuJoCo's thread pool gives bit-identical results at any thread count (0 = every core).
    env_all = VecEnv("inverted_pendulum", num_envs=3, episode_length=50, physics="native", physics_threads=0)
    assert env_all.env.host.nthread >= 1
    for a, b in zip(
        jax.tree.leaves(jax.jit(make_run(env_all))(keys[0])), jax.tree.leaves(again), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(np.asarray(outs[1][0]), np.asarray(outs[1][1])), "seeds differ"


def test_training_iteration_with_native_physics_runs_under_jit_and_is_reproducible():
    """The whole PPO iteration, callback included, is one jitted function; same seed, same result."""
    cfg = parse_overrides(
        [
            "env=inverted_pendulum",
            "physics=native",
            "num_envs=4",
            "unroll_length=8",
            "ppo.num_minibatches=2",
            "ppo.num_epochs=1",
            "eval_episodes=2",
            "episode_length=20",
            "policy_hidden=[8]",
            "value_hidden=[8]",
        ]
    )
    trainer = OnPolicyTrainer(cfg)
    assert trainer.env.physics == trainer.eval_env.physics == "native"
    init = jax.jit(trainer.init)
    iteration = jax.jit(trainer.iteration)

    def run(seed):
        state = init(jax.random.PRNGKey(seed))
        for _ in range(3):
            state, metrics = iteration(state)
        return state, metrics

    state_a, metrics_a = run(0)
    state_b, _ = run(0)
    state_c, _ = run(1)
    assert isinstance(state_a.env_state.physics, NativeState)
    assert all(np.isfinite(float(v)) for v in metrics_a.values())
    leaves_a, leaves_b, leaves_c = (jax.tree.leaves(s.params) for s in (state_a, state_b, state_c))
    for a, b in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert any(
        not np.array_equal(np.asarray(a), np.asarray(c)) for a, c in zip(leaves_a, leaves_c, strict=True)
    )


def test_physics_choice_and_refusals():
    """auto picks native on CPU where it exists; native refuses other tasks naming the allowed ones."""
    assert jax.default_backend() == "cpu"
    assert resolve_physics("halfcheetah", "auto") == "native"
    assert resolve_physics("brax-halfcheetah", "auto") == "native"
    assert resolve_physics("brax-halfcheetah", "mjx") == "mjx"
    assert resolve_physics("pointmass", "auto") == "jax"
    assert resolve_physics("brax-humanoid", "auto") == "mjx"
    assert resolve_physics("humanoid", "native") == "native"
    with pytest.raises(PhysicsError) as err:
        resolve_physics("brax-humanoid", "native")
    assert "'brax-humanoid'" in str(err.value) and all(t in str(err.value) for t in NATIVE_TASKS)
    with pytest.raises(PhysicsError, match="'warp'.*auto, mjx, native"):
        resolve_physics("halfcheetah", "warp")
    with pytest.raises(ConfigError, match="'physics'.*auto, mjx, native"):
        parse_overrides(["physics=warp"])
    with pytest.raises(ConfigError, match="'physics_threads'.*>= 0"):
        parse_overrides(["physics_threads=-1"])
    with pytest.raises(ConfigError) as err:
        parse_overrides(["env=brax-swimmer", "physics=native"])
    assert "'brax-swimmer'" in str(err.value) and "halfcheetah" in str(err.value)
    assert parse_overrides(["env=brax-halfcheetah", "physics=mjx"]).physics == "mjx"
    # Gymnasium's tasks run their own model on MJX, but for Humanoid-v5 (PGS): refused in validation.
    assert parse_overrides(["physics=mjx"]).physics == "mjx"
    with pytest.raises(ConfigError, match="'physics': 'mjx' with env=humanoid.*PGS.*brax-humanoid"):
        parse_overrides(["env=humanoid", "physics=mjx"])


def test_bench_physics_bad_input_exits_2_and_writes_nothing(tmp_path, capsys):
    from benchmarks.__main__ import main

    out = tmp_path / "physics.json"
    for bad, key in (
        ("envs=[0]", "'envs'"),
        ("variants=[warp]", "'variants'"),
        ("env=brax-swimmer", "'env'"),
    ):
        assert main(["physics", bad, f"out={out}"]) == 2
        err = capsys.readouterr().err
        assert key in err and "allowed" in err and len(err.strip().splitlines()) == 1
    assert main(["physics", "physics=mjx"]) == 2 and "unknown key 'physics'" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_bench_physics_measures_and_writes_json(tmp_path):
    """A tiny real run (native MuJoCo without JAX, so no compile): one row per variant and count."""
    import json

    from benchmarks.__main__ import main

    out = tmp_path / "physics.json"
    args = ["env=inverted_pendulum", "envs=[2,4]", "variants=[native_raw]", "steps=5", "repeats=1"]
    assert main(["physics", *args, f"out={out}"]) == 0
    result = json.loads(out.read_text())
    assert [(r["variant"], r["n"]) for r in result["rows"]] == [("native_raw", 2), ("native_raw", 4)]
    assert all(r["env_steps_per_s"] > 0 and "error" not in r for r in result["rows"])


def test_bench_standard_bad_input_exits_2_and_writes_nothing(tmp_path, capsys):
    from benchmarks.__main__ import main

    out = tmp_path / "standard.json"
    for bad, key in (("tasks=[cheetah]", "'tasks'"), ("envs=[0]", "'envs'"), ("repeats=0", "'repeats'")):
        assert main(["standard", bad, f"out={out}"]) == 2
        err = capsys.readouterr().err
        assert key in err and "allowed" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
