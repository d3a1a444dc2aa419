"""Batched small-matrix linear algebra for the joint form of the coherent marginals.

The loss factors one T x T covariance per (segment, action dimension): about a hundred
64 x 64 matrices per minibatch. LAPACK's factorisation of each is quick, but JAX's
reverse pass through it (two triangular solves with T right-hand sides per matrix,
called matrix by matrix) was most of the loss's gradient on CPU, and so were the forward
solves. Here both passes are matrix products with L^-1, and L^-1 itself comes from
products of blocks that double in size, vectorised across every matrix of the batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# Below this block size the doubling's products are written as broadcasts and sums
# (one fused loop over the whole batch) rather than as batched dots, which XLA's CPU
# backend runs one small matrix at a time: 2x faster for 96 matrices of 64 x 64.
_SMALL_BLOCK = 4


def tril_inverse(chol: jax.Array) -> jax.Array:
    """L^-1 of lower-triangular matrices [..., T, T] by doubling diagonal blocks.

    With L = [[A, 0], [B, C]], L^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]]: starting
    from the 1 x 1 blocks 1 / L_tt, each of log2(T) rounds joins neighbouring blocks.
    T is padded to a power of two with an identity block (whose inverse is itself).
    """
    t = chol.shape[-1]
    size = 1 << max(t - 1, 0).bit_length()
    lead = chol.shape[:-2]
    if size != t:
        eye = jnp.broadcast_to(jnp.eye(size, dtype=chol.dtype), (*lead, size, size))
        chol = eye.at[..., :t, :t].set(chol)
    inv = (1.0 / jnp.diagonal(chol, axis1=-2, axis2=-1))[..., :, None, None]  # [..., T, 1, 1]
    s = 1
    while s < size:
        nb = size // s
        blocks = chol.reshape(*lead, nb, s, nb, s)
        # B of each pair: the rows of block 2k+1, the columns of block 2k.
        lower = jnp.moveaxis(jnp.diagonal(blocks[..., 1::2, :, 0::2, :], axis1=-4, axis2=-2), -1, -3)
        a_inv, c_inv = inv[..., 0::2, :, :], inv[..., 1::2, :, :]
        mm = _broadcast_matmul if s <= _SMALL_BLOCK else jnp.matmul
        off = -mm(mm(c_inv, lower), a_inv)
        top = jnp.concatenate([a_inv, jnp.zeros_like(off)], axis=-1)
        bottom = jnp.concatenate([off, c_inv], axis=-1)
        inv = jnp.concatenate([top, bottom], axis=-2)
        s *= 2
    return inv[..., 0, :t, :t]


def _broadcast_matmul(x: jax.Array, y: jax.Array) -> jax.Array:
    return jnp.sum(x[..., :, :, None] * y[..., None, :, :], axis=-2)


def _phi(x: jax.Array) -> jax.Array:
    """Lower triangle with the diagonal halved: dL = L Phi(L^-1 dK L^-T) (Murray, 2016, eq. 8)."""
    return jnp.tril(x) - 0.5 * x * jnp.eye(x.shape[-1], dtype=x.dtype)


def _factor(cov: jax.Array, resid: jax.Array, cross: jax.Array):
    # LAPACK reads the lower triangle only; ``jnp.linalg.cholesky`` would first average K
    # with its transpose, a transposing copy that cost a tenth of the loss's gradient.
    chol = jax.lax.linalg.cholesky(cov, symmetrize_input=False)
    # Products with M = L^-1 rather than triangular solves: XLA's CPU backend solves
    # matrix by matrix, and the reverse pass needs M anyway.
    inv = tril_inverse(chol)
    white = jnp.einsum("...ts,...s->...t", inv, resid)
    proj = inv @ cross
    return inv, white, jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), proj


@jax.custom_vjp
def whiten(cov: jax.Array, resid: jax.Array, cross: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(z, log diag L, Y) with K = L L' (Cholesky, lower), z = L^-1 r and Y = L^-1 C.

    Batched over leading axes. The factor is LAPACK's; M = L^-1 comes from
    `tril_inverse`, and z and Y are products with it. The reverse pass, for cotangents
    (zbar, gbar, Ybar): with S = M dK M', dL = L Phi(S) gives dM = -Phi(S) M, so
    dz = -Phi(S) z + M dr, dY = -Phi(S) Y + M dC and d log L_tt = S_tt / 2, hence

        Kbar = sym(M' [diag(gbar) / 2 - Phi(zbar z' + Ybar Y')] M),
        rbar = M' zbar,   Cbar = M' Ybar,

    the gradient with respect to a symmetric K. Only K's lower triangle is read, so K
    must be symmetric by construction (as `masked_gram`'s is); it is not symmetrised
    here. Row i of Phi(zbar z') M is zbar_i (sum_{j <= i} z_j M_j - z_i M_i / 2), a
    running sum over rows, so the marginals' terms take no matrix product at all.
    Equal to JAX's own reverse pass of a Cholesky factor and triangular solves to float64
    rounding (tests/test_coherent_joint.py).

    Args:
      cov: [..., T, T] symmetric positive definite.
      resid: [..., T].
      cross: [..., T, k] further right-hand sides (k may be 0).

    Returns:
      (z [..., T], log diag L [..., T], Y [..., T, k]).
    """
    _, white, log_diag, proj = _factor(cov, resid, cross)
    return white, log_diag, proj


def _whiten_fwd(cov, resid, cross):
    # With symbolic zeros the primals come wrapped (``CustomVJPPrimal``).
    inv, white, log_diag, proj = _factor(cov.value, resid.value, cross.value)
    return (white, log_diag, proj), (inv, white, proj)


def _whiten_bwd(res, cotangents):
    inv, white, proj = res
    white_bar, log_diag_bar, proj_bar = cotangents
    zero = jax.custom_derivatives.SymbolicZero
    if isinstance(white_bar, zero):
        white_bar = jnp.zeros_like(white)
    # middle @ M, with middle = diag(gbar) / 2 - Phi(zbar z') - Phi(Ybar Y').
    # sum_{j <= i} z_j M_j; a prefix sum in log2(T) rounds (XLA's CPU cumsum is a T-wide window).
    running = jax.lax.associative_scan(jnp.add, white[..., :, None] * inv, axis=-2)
    middle_inv = -white_bar[..., :, None] * (running - 0.5 * white[..., :, None] * inv)
    if not isinstance(log_diag_bar, zero):
        middle_inv = middle_inv + 0.5 * log_diag_bar[..., :, None] * inv
    if isinstance(proj_bar, zero):
        cross_bar = jnp.zeros_like(proj)
    else:  # the end-of-segment belief reads Y
        middle_inv = middle_inv - _phi(proj_bar @ jnp.swapaxes(proj, -1, -2)) @ inv
        cross_bar = jnp.swapaxes(inv, -1, -2) @ proj_bar
    cov_bar = jnp.swapaxes(inv, -1, -2) @ middle_inv
    cov_bar = 0.5 * (cov_bar + jnp.swapaxes(cov_bar, -1, -2))
    resid_bar = jnp.einsum("...ts,...t->...s", inv, white_bar)
    return cov_bar, resid_bar, cross_bar


whiten.defvjp(_whiten_fwd, _whiten_bwd, symbolic_zeros=True)


@jax.custom_vjp
def masked_gram(x: jax.Array, var: jax.Array, mask: jax.Array, noise_var: jax.Array) -> jax.Array:
    """K_i = mask * (X diag(var_i) X') + noise_var_i I, one T x T matrix per row i of ``var``.

    The covariance of the joint form
    (`coherent_jax.exploration.coherent.joint.segment_marginals_joint`), symmetric
    whenever ``mask`` is. Its reverse pass uses that symmetry: with G_i = mask * Kbar_i and
    S_i = G_i + G_i', one product Y_i = S_i X per matrix gives

        Xbar = sum_i Y_i diag(var_i),   varbar_i = sum_s X_s * Y_i,s / 2,

    where differentiating the two sides of X D X' separately takes two products (and a
    transposed copy of Kbar for the second). Any cotangent Kbar is handled, symmetric or
    not; ``maskbar`` and ``noise_varbar`` are sum_i Kbar_i * (X D_i X') and tr Kbar_i.

    Args:
      x: [T, n] features.
      var: [p, n] the diagonal of each D_i.
      mask: [T, T] elementwise factor (the chain's (1-beta)^|s-t| within an episode).
      noise_var: [p] added to each diagonal.

    Returns:
      [p, T, T].
    """
    return _masked_gram_fwd(x, var, mask, noise_var)[0]


def _masked_gram_fwd(x, var, mask, noise_var):
    gram = jnp.einsum("isk,tk->ist", x[None, :, :] * var[:, None, :], x)  # X D_i X'
    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    cov = mask[None] * gram + noise_var[:, None, None] * eye[None]
    return cov, (x, var, mask, gram)


def _masked_gram_bwd(res, cov_bar):
    x, var, mask, gram = res
    sym = mask[None] * (cov_bar + jnp.swapaxes(cov_bar, -1, -2))  # S_i
    y = jnp.einsum("ist,tk->isk", sym, x)  # [p, T, n]
    # Sums of products rather than einsums: as dots these transposed y twice.
    x_bar = jnp.sum(y * var[:, None, :], axis=0)
    var_bar = 0.5 * jnp.sum(y * x[None], axis=1)
    mask_bar = jnp.sum(cov_bar * gram, axis=0)
    noise_var_bar = jnp.sum(jnp.diagonal(cov_bar, axis1=-2, axis2=-1), axis=-1)
    return x_bar, var_bar, mask_bar, noise_var_bar


masked_gram.defvjp(_masked_gram_fwd, _masked_gram_bwd)
