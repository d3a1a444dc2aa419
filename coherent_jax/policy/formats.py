"""A `Policy`'s deterministic action out of Python: ONNX and serialized StableHLO.

It stands alone because it is a public module (``coherent_jax.policy.formats``, docs/api.md)
and because it keeps onnx, an optional dependency, out of every import but `write_onnx`'s:
`coherent_jax.policy.onnx_graph` needs onnx, StableHLO only JAX.

Both hold the whole evaluation action, a = m(clip(mu(norm(s)), -1, 1)) (observation
normalisation, the algorithm's mean, the task's `ActionMap`), on a batch ``obs`` [N, o]
float32 -> ``action`` [N, p] float32:

* ONNX (`write_onnx`): the graph `coherent_jax.policy.onnx_graph` writes from the jaxpr; it
  runs under onnxruntime (or any ONNX runtime) without JAX or this package.
* StableHLO (`write_stablehlo`): ``jax.export`` of the same function with a symbolic batch
  size, serialized; ``jax.export.deserialize(blob).call(obs)`` runs it with JAX alone.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.policy.trained import Policy


def action_fn(policy: Policy):
    """obs [..., o] -> the deterministic action [..., p] in the env's action space, parameters closed over."""
    inner, amap = policy.policy, policy.action_map
    return lambda obs: amap(inner.mean_action(obs))


def write_onnx(policy: Policy, path: Path) -> None:
    """The ONNX model of the policy's deterministic action (inputs ``obs`` [N, o], output ``action``)."""
    from coherent_jax.policy.onnx_graph import to_onnx  # lazy: onnx, an optional dependency (export extra)

    doc = repr(policy)
    model = to_onnx(action_fn(policy), policy.obs_size, policy.action_size, doc)
    path.write_bytes(model.SerializeToString())


def write_stablehlo(policy: Policy, path: Path) -> None:
    """``jax.export`` of the deterministic action on ``obs`` [b, o] float32, b symbolic, serialized."""
    (b,) = jax.export.symbolic_shape("b")
    spec = jax.ShapeDtypeStruct((b, policy.obs_size), jnp.float32)
    exported = jax.export.export(jax.jit(action_fn(policy)))(spec)
    path.write_bytes(bytes(exported.serialize()))


def run_stablehlo(blob: bytes, obs: np.ndarray) -> np.ndarray:
    """Actions of a `write_stablehlo` file for ``obs`` [N, o] (JAX alone)."""
    return np.asarray(jax.export.deserialize(bytearray(blob)).call(jnp.asarray(obs, jnp.float32)))
