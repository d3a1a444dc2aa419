"""A policy's deterministic action as an ONNX graph, written from its jaxpr (no exporter package).

The function exported is one observation -> one action, s -> m(clip(mu(norm(s)), -1, 1)) (the
observation normalisation, the algorithm's mean and the task's `ActionMap`, as
`coherent_jax.policy.Policy.predict` computes it), traced to a jaxpr with the
parameters as constants. The graph acts on a batch ``obs`` [N, o] -> ``action`` [N, p]:

* every equation whose inputs are all constants (parameters, the action bounds, literals)
  is evaluated here, in float32, and stored as an initializer;
* every equation that depends on the observation becomes ONNX nodes on values with a
  leading batch axis (an unbatched value of shape s is [N, *s] in the graph), which
  ONNX's numpy-style broadcasting lines up with the constants on the right;
* calls (``jit``, ``custom_jvp_call``, ``custom_vjp_call``) are inlined.

It covers the primitives of this package's policies (MLP layers, LayerNorm, tanh/relu/
elu/swish-style activations, clipping, the affine action map); any other primitive is
refused by name, so an export never silently differs from JAX. `tests/test_export.py`
checks onnxruntime against ``predict(deterministic=True)`` for every strategy.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
_UNARY = {
    "tanh": "Tanh",
    "exp": "Exp",
    "log": "Log",
    "neg": "Neg",
    "abs": "Abs",
    "sqrt": "Sqrt",
    "logistic": "Sigmoid",
    "erf": "Erf",
    "sign": "Sign",
    "floor": "Floor",
    "ceil": "Ceil",
}
_BINARY = {
    "add": "Add",
    "sub": "Sub",
    "mul": "Mul",
    "div": "Div",
    "max": "Max",
    "min": "Min",
    "pow": "Pow",
    "gt": "Greater",
    "lt": "Less",
    "ge": "GreaterOrEqual",
    "le": "LessOrEqual",
    "eq": "Equal",
}
_IDENTITY = ("stop_gradient", "copy", "copy_p", "optimization_barrier")
_CALLS = {"pjit": "jaxpr", "jit": "jaxpr", "closed_call": "call_jaxpr", "custom_jvp_call": "call_jaxpr"}


class ExportError(ValueError):
    """A policy whose graph uses a primitive the ONNX writer does not translate."""


class _Writer:
    """Walks a jaxpr; ``env`` maps each var to ("const", ndarray) or ("batched", onnx name)."""

    def __init__(self) -> None:
        self.nodes: list[Any] = []
        self.inits: list[Any] = []
        self.count = 0

    def name(self, hint: str) -> str:
        self.count += 1
        return f"{hint}_{self.count}"

    def const(self, value: Any) -> str:
        arr = np.asarray(value)
        if arr.dtype == np.float64:
            arr = arr.astype(np.float32)
        name = self.name("c")
        self.inits.append(numpy_helper.from_array(arr, name))
        return name

    def node(self, op: str, inputs: list[str], hint: str = "v", **attrs: Any) -> str:
        out = self.name(hint)
        self.nodes.append(helper.make_node(op, inputs, [out], **attrs))
        return out

    def ints(self, values: Any) -> str:
        return self.const(np.asarray(values, np.int64))

    # -------------------------------------------------------------- the walk
    def run(self, jaxpr: Any, consts: list[Any], args: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
        env: dict[Any, tuple[str, Any]] = {}

        def read(v: Any) -> tuple[str, Any]:
            if hasattr(v, "val") and not hasattr(v, "count"):  # a Literal
                return ("const", np.asarray(v.val))
            return env[v]

        for v, c in zip(jaxpr.constvars, consts, strict=True):
            env[v] = ("const", np.asarray(c))
        for v, a in zip(jaxpr.invars, args, strict=True):
            env[v] = a
        for eqn in jaxpr.eqns:
            ins = [read(v) for v in eqn.invars]
            outs = self.eqn(eqn, ins)
            for v, o in zip(eqn.outvars, outs, strict=True):
                env[v] = o
        return [read(v) for v in jaxpr.outvars]

    def eqn(self, eqn: Any, ins: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
        prim = eqn.primitive.name
        key = _CALLS.get(prim) or ("call_jaxpr" if prim.startswith("custom_vjp_call") else None)
        if key is not None:
            closed = eqn.params[key]
            return self.run(closed.jaxpr, list(closed.consts), ins)
        if all(kind == "const" for kind, _ in ins):
            vals = eqn.primitive.bind(*[v for _, v in ins], **eqn.params)
            vals = vals if eqn.primitive.multiple_results else [vals]
            return [("const", np.asarray(v)) for v in vals]
        if len(eqn.outvars) != 1:
            raise ExportError(f"unsupported primitive {prim!r} in the policy's graph")
        out_shape = tuple(eqn.outvars[0].aval.shape)
        return [("batched", (self.batched(prim, eqn.params, ins, out_shape), len(out_shape), out_shape))]

    def operand(self, value: tuple[str, Any], out_rank: int) -> str:
        """An input of an elementwise node: a constant as is, a batched scalar reshaped
        to [N, 1, ..] so that it broadcasts against the other unbatched axes."""
        kind, v = value
        if kind == "const":
            return self.const(v)
        if v[1] < out_rank:  # batched value of lower rank (a scalar)
            return self.node("Reshape", [v[0], self.ints([-1] + [1] * out_rank)])
        return v[0]

    def batched(self, prim: str, params: dict, ins: list, out_shape: tuple) -> str:
        rank = len(out_shape)
        x = ins[0][1][0] if ins[0][0] == "batched" else None
        if prim in _UNARY:
            return self.node(_UNARY[prim], [x])
        if prim in _BINARY:
            return self.node(_BINARY[prim], [self.operand(v, rank) for v in ins])
        if prim in _IDENTITY:
            return x
        if prim == "convert_element_type":
            if np.dtype(params["new_dtype"]) != np.float32:
                raise ExportError(f"unsupported cast to {params['new_dtype']} in the policy's graph")
            return self.node("Cast", [x], to=TensorProto.FLOAT)
        if prim == "square":
            return self.node("Mul", [x, x])
        if prim == "rsqrt":
            return self.node("Reciprocal", [self.node("Sqrt", [x])])
        if prim == "integer_pow":
            return self.node("Pow", [x, self.const(np.float32(params["y"]))])
        if prim == "log1p":
            return self.node("Log", [self.node("Add", [x, self.const(np.float32(1))])])
        if prim == "expm1":
            return self.node("Sub", [self.node("Exp", [x]), self.const(np.float32(1))])
        if prim == "clamp":  # clamp(lo, x, hi)
            lo, val, hi = (self.operand(v, rank) for v in ins)
            return self.node("Min", [self.node("Max", [val, lo]), hi])
        if prim == "select_n":  # select_n(pred, *cases): case[pred]
            if len(ins) != 3:
                raise ExportError("unsupported select_n of more than two cases in the policy's graph")
            pred, f, t = (self.operand(v, rank) for v in ins)
            pred = self.node("Cast", [pred], to=TensorProto.BOOL)
            return self.node("Where", [pred, t, f])
        if prim in ("reduce_sum", "reduce_max", "reduce_min"):
            op = {"reduce_sum": "ReduceSum", "reduce_max": "ReduceMax", "reduce_min": "ReduceMin"}[prim]
            axes = [a + 1 for a in params["axes"]]
            if op == "ReduceSum":
                return self.node(op, [x, self.ints(axes)], keepdims=0)
            return self.node(op, [x], axes=axes, keepdims=0)
        if prim in ("reshape", "squeeze", "expand_dims"):
            return self.node("Reshape", [x, self.ints([-1, *out_shape])])
        if prim == "broadcast_in_dim":
            dims, shape = params["broadcast_dimensions"], params["shape"]
            inner = [1] * len(shape)
            for d, s in zip(dims, ins[0][1][2], strict=True):
                inner[d] = s
            y = self.node("Reshape", [x, self.ints([-1, *inner])])
            return self.node("Expand", [y, self.ints([1, *shape])])
        if prim == "concatenate":
            parts = [self.expand(v) for v in ins]
            return self.node("Concat", parts, axis=params["dimension"] + 1)
        if prim == "dot_general":
            return self.dot(params, ins)
        raise ExportError(f"unsupported primitive {prim!r} in the policy's graph")

    def expand(self, value: tuple[str, Any]) -> str:
        """A value as [N, *shape]: a constant repeated along the batch."""
        kind, v = value
        if kind == "batched":
            return v[0]
        c = self.const(np.asarray(v)[None])
        shape = self.node("Concat", [self.batch, self.ints(np.shape(v))], axis=0)
        return self.node("Expand", [c, shape])

    def dot(self, params: dict, ins: list) -> str:
        """x . W: a batched value contracted on its last axis with a constant matrix, or a
        constant matrix times a batched vector."""
        (lc, rc), (lb, rb) = params["dimension_numbers"]
        (lk, lv), (rk, rv) = ins
        if lb or rb or len(lc) != 1:
            raise ExportError("unsupported dot_general (batch dimensions) in the policy's graph")
        if lk == "batched" and rk == "const" and lc[0] == lv[1] - 1 and np.ndim(rv) == 2:
            w = np.moveaxis(np.asarray(rv), rc[0], 0)  # x [N, .., k] @ w [k, m]
            return self.node("MatMul", [lv[0], self.const(w)])
        if rk == "batched" and lk == "const" and rv[1] == 1:
            w = np.moveaxis(np.asarray(lv), lc[0], -1)  # [m, k] -> x [N, k] @ w.T
            return self.node("MatMul", [rv[0], self.const(w.reshape(-1, w.shape[-1]).T)])
        raise ExportError("unsupported dot_general (not a vector times a matrix) in the policy's graph")


def to_onnx(fn: Any, obs_size: int, action_size: int, doc: str = "") -> onnx.ModelProto:
    """The ONNX model of ``fn`` (one observation [obs_size] float32 -> one action [action_size]),
    acting on a batch ``obs`` [N, obs_size] -> ``action`` [N, action_size]."""
    closed = jax.make_jaxpr(fn)(np.zeros((obs_size,), np.float32))
    w = _Writer()
    w.batch = w.node("Slice", [w.node("Shape", ["obs"]), w.ints([0]), w.ints([1])], "batch")
    # values carry (name, unbatched rank, unbatched shape)
    (out,) = w.run(closed.jaxpr, list(closed.consts), [("batched", ("obs", 1, (obs_size,)))])
    name = w.expand(out)
    w.nodes.append(helper.make_node("Identity", [name], ["action"]))
    graph = helper.make_graph(
        w.nodes,
        "policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", obs_size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", action_size])],
        w.inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], doc_string=doc)
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model
