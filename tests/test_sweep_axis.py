"""A sweep's conds branch once for all its points (`coherent_jax.sweep_axis`), and the
points still compute what each would alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.agents.onpolicy import OnPolicyTrainer
from coherent_jax.config import parse_overrides
from coherent_jax.sweep_axis import all_points, any_point, vmap_points

TINY = [
    "env=pointmass",
    "num_envs=4",
    "unroll_length=6",
    "ppo.num_minibatches=2",
    "ppo.num_epochs=2",
    "eval_episodes=2",
    "policy_hidden=[16,16]",
    "value_hidden=[16,16]",
    "episode_length=9",
]


def test_reductions_over_the_points_and_outside_a_sweep():
    def both(pred):
        return any_point(pred), all_points(pred)

    preds = jnp.array([True, False, False])
    anys, alls = vmap_points(both)(preds)
    np.testing.assert_array_equal(anys, [True, True, True])
    np.testing.assert_array_equal(alls, [False, False, False])
    np.testing.assert_array_equal(vmap_points(both)(jnp.array([True, True]))[1], [True, True])
    # Outside a sweep (and under a vmap of another name) the predicate is left as it is.
    assert jax.jit(both)(jnp.array(False)) == (False, False)
    np.testing.assert_array_equal(jax.vmap(both)(preds)[0], preds)


def count_conds(jaxpr) -> int:
    """`cond` equations in a closed jaxpr, nested ones included."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == "cond"
        for sub in jax.core.jaxprs_in_params(eqn.params):
            n += count_conds(sub)
    return n


def stacked_states(trainer):
    """Two points' states in different episode phases (the first ran one iteration more)."""
    single = jax.jit(trainer.iteration)
    ahead, _ = single(trainer.init(jax.random.PRNGKey(0)))
    states = [ahead, trainer.init(jax.random.PRNGKey(1))]
    return single, states, jax.tree.map(lambda *x: jnp.stack(x), *states)


@pytest.mark.parametrize("explore", ["action", "pink", "psne"])
def test_sweep_iteration_keeps_its_conds(explore):
    """Under a plain vmap the conds of env resets and episode draws (psne: also the
    loss's layout) become selects that compute both branches at every point; under
    `vmap_points` they stay conds."""
    trainer = OnPolicyTrainer(parse_overrides([*TINY, "algo=ppo", f"explore={explore}"]))
    shapes = jax.eval_shape(jax.vmap(trainer.init), jax.random.split(jax.random.PRNGKey(0), 2))
    named = jax.make_jaxpr(vmap_points(trainer.iteration))(shapes).jaxpr
    plain = jax.make_jaxpr(jax.vmap(trainer.iteration))(shapes).jaxpr
    assert count_conds(named) >= count_conds(plain) + {"action": 1, "pink": 2, "psne": 4}[explore]


@pytest.mark.slow
def test_each_point_of_a_sweep_runs_as_alone():
    """Pink noise (conds of env resets and episode draws): the points differ in their
    episode phase, so their predicates differ; each point's next iterations equal that
    point's own. (PSNE's third cond chooses between two layouts of one computation:
    `test_psne_minibatch_log_prob_draws_each_episode_once_and_equals_per_segment`.)"""
    trainer = OnPolicyTrainer(parse_overrides([*TINY, "algo=ppo", "explore=pink"]))
    single, states, stacked = stacked_states(trainer)
    step = jax.jit(vmap_points(trainer.iteration))
    for _ in range(2):
        stacked, metrics = step(stacked)
        outs = [single(s) for s in states]
        states = [o[0] for o in outs]
        for i, (state, m) in enumerate(outs):
            for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(stacked.params), strict=True):
                np.testing.assert_allclose(b[i], a, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(
                metrics["train/policy_loss"][i], m["train/policy_loss"], rtol=1e-3, atol=1e-5
            )
    firsts = [np.asarray(s.env_state.first) for s in states]
    assert not np.array_equal(firsts[0], firsts[1])
