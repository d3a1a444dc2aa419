"""The thesis's estimator over long episodes: marginals re-inferred from the episode start.

Coherent-A2C/PPO differentiate log p(a_t | a_<t, s_<=t) with the whole history of
the chain's episode integrated out under the current parameters (Algorithm 5, steps
12-16; eqs. 4.14, 4.33-4.49). A belief stored at collection and held fixed as a
constant of the data gives the right values but not that gradient: the history's
trunk features, mu and w_std all move the belief a later step conditions on.

`chained_marginals` gives the exact quantity at a cost linear in the episode length: it
scores a long segment as a chain of blocks of the joint form
(`joint.segment_marginals_joint`), each block starting from the belief the block
before it ends with, *not* stopped: the gradient flows through every belief back to the
start of the chain. O(T (B (q+1) + (q+1)^2)) per action dimension for blocks of B steps,
instead of the single joint form's O(T^2 (q+1) + T^3).

The trainer's exact mode needs neither prefix nor stored belief: it restarts the chain
at each segment start, as Algorithm 5 does at t = 0 of every buffer (steps 4-5), so
every segment is scored from the prior by `chained_marginals`. Its episode mode
(``coherent.gradient=episode``) scores a segment that starts mid-episode by running the
same chain over the episode prefix (its features, actions and resets) first, so the
segment's log-probabilities condition on the prefix re-inferred under the current
parameters (`strategy.CoherentExploration`); its cost grows as (prefix + segment) /
segment.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.chain import ChainParams
from coherent_jax.exploration.coherent.filter import Belief
from coherent_jax.exploration.coherent.joint import segment_marginals_joint

#: blocks of at most this many steps; 64 is where the joint form's T^2 and T^3 terms stay
#: below its (q+1)^2 belief terms at q = 64 (see `chained_marginals`).
MAX_BLOCK = 64


def block_size(num_steps: int, max_block: int = MAX_BLOCK) -> int:
    """The largest divisor of ``num_steps`` that is at most ``max_block`` (static)."""
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    return max(b for b in range(1, min(num_steps, max_block) + 1) if num_steps % b == 0)


def chained_marginals(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
    block: int | None = None,
    from_prior: bool = False,
    remat: bool = False,
    start_block: chex.Array | None = None,
) -> tuple[chex.Array, Belief, chex.Array]:
    """`filter.segment_marginals` over T steps, as blocks of the joint form chained by beliefs.

    The segment is cut into T / B blocks of B steps. Block k is scored from its joint
    Gaussian (eqs. 4.37/4.49 through the Cholesky factor, as in
    `segment_marginals_joint`) starting from alpha(w) at its first step, the posterior
    (4.44)-(4.46) the block before it ends with; ``first`` resets to the prior (4.33)
    inside any block. The beliefs between blocks are differentiable functions of the
    parameters and of every earlier step's inputs, so the gradient of any function of
    the log-probabilities is that of the sequential filter over the whole segment.

    Per action dimension and step this costs about 3 B (q+1) + B^2 / 3 + 2 (q+1)^2
    multiply-adds against the filter's 3 (q+1)^2, with no sequential loop inside a block.
    The reverse pass keeps each block's intermediates, O(T (B + (q+1)^2 / B)) floats per
    action dimension, instead of the single joint form's O(T^2); with ``remat`` it keeps
    only the beliefs between blocks and recomputes each block (about a third more time).

    Args:
      belief0: alpha(w_0) of the segment, mean [p, q+1], cov [p, q+1, q+1]; used at
        t = 0 unless ``first[0]``. Gradients flow into it if it is traced.
      x: [T, q] last-layer inputs.
      a: [T, p] actions taken.
      first: [T] bool, True where an episode starts at t.
      params: the chain's mu [p, q+1] (bias last), w_std [p, q+1], action_std [p] and
        beta, a scalar in [0, 1].
      block: steps per block, a divisor of T; default `block_size(T)`.
      from_prior: the segment starts an episode (``belief0`` unused); the first block
        then skips the stored belief's terms (`segment_marginals_joint`).
      remat: ``jax.checkpoint`` each block (static).
      start_block: an integer scalar k0, or None. Block 0 is always scored; blocks
        1 .. k0 - 1 are skipped: the belief passes through them unchanged, their logp
        are 0 and their variances 1. Only right where every step that is kept
        conditions on nothing before block k0, i.e. each kept step's episode starts at
        or after step k0 B (the episode mode's windows, `strategy.window_start_block`).
        A ``jax.lax.cond`` per block, so a k0 that is the same for a whole batch skips
        its work; under ``vmap`` over k0 both branches run.

    Returns:
      (logp [T], the belief over w_T before a_T, the predictive variances s [T, p]).
    """
    chex.assert_rank([x, a, first], [2, 2, 1])
    num_steps = x.shape[0]
    block = block_size(num_steps) if block is None else int(block)
    if num_steps % block:
        raise ValueError(f"block={block} does not divide the segment length {num_steps}")
    num_blocks = num_steps // block
    head = segment_marginals_joint(belief0, x[:block], a[:block], first[:block], params, from_prior)
    if num_blocks == 1:
        return head
    logp0, belief1, pred_var0 = head

    def split(v):
        return v[block:].reshape((num_blocks - 1, block) + v.shape[1:])

    def score(belief, x_k, a_k, first_k):
        logp, belief, pred_var = segment_marginals_joint(belief, x_k, a_k, first_k, params)
        return belief, (logp, pred_var)

    def skip(belief, x_k, a_k, first_k):
        del x_k, a_k, first_k
        return belief, (jnp.zeros_like(logp0), jnp.ones_like(pred_var0))

    def body(belief, inputs):
        k, x_k, a_k, first_k = inputs
        if start_block is None:
            return score(belief, x_k, a_k, first_k)
        return jax.lax.cond(k >= start_block, score, skip, belief, x_k, a_k, first_k)

    # The belief is the only state passed between blocks; with remat the backward pass
    # recomputes each block's [p, B, B] factor from it instead of keeping all of them.
    body = jax.checkpoint(body) if remat else body
    index = jnp.arange(1, num_blocks)
    final, (logp, pred_var) = jax.lax.scan(body, belief1, (index, split(x), split(a), split(first)))
    logp = jnp.concatenate([logp0, logp.reshape(-1)])
    return logp, final, jnp.concatenate([pred_var0, pred_var.reshape(-1, pred_var0.shape[-1])])
