"""The overlap probe (``python -m benchmarks overlap``): its two ways of stepping K env groups
give the same transitions, its runtime check, and its input errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.overlap import runtime_check
from benchmarks.overlap_groups import TwoPhaseHost, grouped_unroll, pipelined_unroll
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.exploration.base import ActOutput


def test_pipeline_steps_the_same_envs_as_independent_groups():
    """The ring (physics on a host worker between two callbacks) and the independent groups
    draw with the same per-group keys: the same transitions and final states. The MuJoCo
    state rows are equal bit for bit; the task's formulas and the log-probability to float
    rounding, because XLA fuses the two programs' elementwise ops differently. Episodes of
    12 steps over 30 make the auto-reset run inside both."""
    n, groups, length = 4, 2, 30

    def envs():
        return [VecEnv("halfcheetah", n // groups, 12, "native") for _ in range(groups)]

    def act(key, carry, obs, first):
        action = jnp.tanh(obs[:, :6]) + 0.3 * jax.random.normal(key, (obs.shape[0], 6))
        return ActOutput(action, action.sum(-1), carry + 1)

    state = jax.jit(VecEnv("halfcheetah", n, 12, "native").reset)(jax.random.PRNGKey(0))
    key, carry = jax.random.PRNGKey(1), jnp.zeros((n,))
    plain, ring, host = envs(), envs(), TwoPhaseHost()
    a = jax.jit(lambda s, c, k: grouped_unroll(plain, act, s, c, k, length))(state, carry, key)
    b = jax.jit(lambda s, c, k: pipelined_unroll(ring, host, act, s, c, k, length))(state, carry, key)
    assert int(a[2].truncated.sum()) == 2 * n and not host._jobs
    np.testing.assert_array_equal(a[0].physics.engine, b[0].physics.engine)
    for (path, x), y in zip(jax.tree_util.tree_flatten_with_path(a)[0], jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-6, atol=1e-6, err_msg=str(path))


@pytest.mark.parametrize(
    "args,named",
    [
        (["groups=[3]"], "'groups'"),
        (["groups=[1,1]"], "'groups'"),
        (["pipeline=[1]"], "'pipeline'"),
        (["physics=mjx"], "'physics'"),
        (["algo=sac"], "'algo'"),
        (["out=/proc/r.json"], "'out'"),
    ],
)
def test_overlap_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, named):
    from benchmarks.__main__ import main

    out = [] if any(a.startswith("out=") for a in args) else [f"out={tmp_path / 'r.json'}"]
    assert main(["overlap", *args, *out]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and named in lines[0], lines
    assert "allowed" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_runtime_check_sees_the_ring_overlap_and_plain_callbacks_not():
    """Two 20 ms sleeping callbacks: XLA's CPU runtime runs them one after the other (their
    sum or more); with one on the ring's worker thread they overlap (sleeping needs no CPU,
    so this holds on a loaded machine)."""
    figures = runtime_check(3)
    assert sorted(figures) == ["in_scan", "top_level", "two_phase"]
    assert figures["top_level"] > 0.95 and figures["in_scan"] > 0.95
    assert figures["two_phase"] < figures["top_level"]
