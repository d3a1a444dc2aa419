"""Can the second CPU core speed up the thesis row? The long chain's loss over two devices.

    PYTHONPATH=. python experiments/two_core_loss.py [OUT.json] [--envs 4] [--steps 1000] [--rounds 7]

Under ``preset=thesis`` a Coherent-PPO policy step scores 4 chains of 1,000 steps
(`coherent_jax.exploration.coherent.exact.chained_marginals`, eqs. 4.37/4.49 chained by the posterior
4.44-4.46); XLA runs that loss on one core. Its envs are independent chains, so the
loss splits over devices with one all-reduce of the gradient. The iteration's rollout,
though, steps MuJoCo's C engine through one host callback per step. This measures both
halves of the question, on ``--envs`` chains of ``--steps`` steps (p = 6 action
dimensions, q = 64 last-layer inputs: HalfCheetah's policy at the thesis's [64, 64]):

1. the loss's value and gradient (with respect to the last-layer inputs x, mu, w_std and
   action_std, weighted by fixed random advantages as in the policy-gradient objective)
   on one device; split over two with `jax.shard_map` (each device its envs, the sum
   and gradient all-reduced); and by XLA's SPMD partitioner from inputs sharded by env.
   The split losses must equal the one-device loss to float32 rounding (checked);
2. a rollout's shape: a scan of ``--steps`` steps, each a small network on [envs, 17]
   observations and one `jax.pure_callback` into numpy, on one device, and replicated
   over two devices with the callback pinned to the first (``sharding=``), the only way
   the physics could stay one call per step while the loss runs on two devices. The
   callback must run once per step in both (checked).

Timings are medians over ``--rounds`` interleaved rounds. The script asks XLA for two
host devices (``XLA_FLAGS=--xla_force_host_platform_device_count=2``) unless XLA_FLAGS
already sets a count. The figures go to OUT.json (default
bench_results/two_core_loss.json); exit status 1 if a check fails, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    ).strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, SingleDeviceSharding  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

from benchmarks import measure  # noqa: E402
from coherent_jax.exploration.chain import ChainParams  # noqa: E402
from coherent_jax.exploration.coherent.exact import chained_marginals  # noqa: E402
from coherent_jax.exploration.coherent.filter import prior_belief  # noqa: E402

P_ACT, Q, OBS = 6, 64, 17
#: the tolerance of the split losses against the one-device loss (float32 sums reordered)
REL_TOL = 1e-4


def problem(envs: int, steps: int, seed: int = 0) -> dict:
    """Random inputs of the loss: tanh features, actions, advantages and the protocol's
    initial noise scales (w_std 0.1, action_std 0.1 as in `mean_credit.py`)."""
    rng = np.random.default_rng(seed)
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return {
        "params": {
            "x": f32(np.tanh(rng.normal(size=(envs, steps, Q)))),
            "mu": f32(0.01 * rng.normal(size=(P_ACT, Q + 1))),
            "w_std": f32(np.full((P_ACT, Q + 1), 0.1)),
            "action_std": f32(np.full(P_ACT, 0.1)),
        },
        "a": f32(0.3 * rng.normal(size=(envs, steps, P_ACT))),
        "adv": f32(rng.normal(size=(envs, steps))),
        "first": jnp.zeros((envs, steps), bool).at[:, 0].set(True),
    }


def objective(params, a, adv, first):
    """sum over envs and steps of adv_t log p(a_t | a_<t, s_<=t), each env one chain from
    its buffer's start at beta = 0.01 (the thesis's value)."""

    def chain(x, a, first, adv):
        belief = prior_belief(params["mu"], params["w_std"])
        logp = chained_marginals(
            belief,
            x,
            a,
            first,
            ChainParams(params["mu"], params["w_std"], params["action_std"], jnp.float32(0.01)),
            from_prior=True,
        )[0]
        return jnp.sum(adv * logp)

    return jnp.sum(jax.vmap(chain)(params["x"], a, first, adv))


def loss_programs(mesh: Mesh) -> dict:
    """The three jitted value-and-gradient programs, by name."""
    grad = jax.value_and_grad(objective)
    env_spec = {"x": P("d"), "mu": P(), "w_std": P(), "action_std": P()}

    def local(params, a, adv, first):
        value, g = grad(params, a, adv, first)
        # x's gradient stays with its envs; the shared parameters' gradients are summed
        shared = {k: jax.lax.psum(v, "d") for k, v in g.items() if k != "x"}
        return jax.lax.psum(value, "d"), {"x": g["x"], **shared}

    sharded = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(env_spec, P("d"), P("d"), P("d")),
        out_specs=(P(), env_spec),
        check_vma=False,  # the custom VJPs of `linalg` return unannotated cotangents
    )
    return {
        "one device": jax.jit(grad),
        "shard_map, 2 devices": jax.jit(sharded),
        "SPMD, 2 devices": jax.jit(grad),
    }


def program_inputs(name: str, data: dict, mesh: Mesh) -> tuple:
    """Each program's inputs: on the default device, or split by env over the mesh."""
    args = (data["params"], data["a"], data["adv"], data["first"])
    if name == "one device":
        return args
    by_env, rep = NamedSharding(mesh, P("d")), NamedSharding(mesh, P())
    params = {k: jax.device_put(v, by_env if k == "x" else rep) for k, v in data["params"].items()}
    return (params,) + tuple(jax.device_put(v, by_env) for v in args[1:])


def rel_err(ref, out) -> float:
    """max over leaves of |out - ref| / max |ref|."""
    errs = jax.tree.map(lambda r, o: float(jnp.max(jnp.abs(o - r)) / jnp.max(jnp.abs(r))), ref, out)
    return max(jax.tree.leaves(errs))


class Callbacks:
    """A numpy stand-in for the physics callback that counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, h):
        self.calls += 1
        return np.asarray(np.tanh(np.asarray(h)), np.float32)


def rollout_program(host: Callbacks, steps: int, sharding) -> Callable:
    """A scan of ``steps`` steps: a 17 -> 64 -> 17 tanh network and one callback per step."""
    w1, w2 = 0.1 * jnp.ones((OBS, 64)), 0.1 * jnp.ones((64, OBS))

    def step(obs, _):
        h = jnp.tanh(jnp.tanh(obs @ w1) @ w2)
        shape = jax.ShapeDtypeStruct(h.shape, h.dtype)
        return jax.pure_callback(host, shape, h, vmap_method="broadcast_all", sharding=sharding), ()

    return lambda obs: jax.lax.scan(step, obs, None, length=steps)[0]


def median_ms(fns: dict, args: dict, rounds: int) -> dict:
    """Median milliseconds by name over ``rounds`` interleaved rounds of one call each
    (`measure.time_calls`); the caller has called each once already (compiled, warm)."""
    times = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            times[name] += measure.time_calls(fn, args[name], 1)
    return {name: 1e3 * float(np.median(v)) for name, v in times.items()}


def run(envs: int, steps: int, rounds: int) -> dict:
    """Both measurements and their checks (see the module docstring)."""
    mesh = Mesh(np.array(jax.devices()[:2]), ("d",))
    data = problem(envs, steps)
    losses = loss_programs(mesh)
    args = {name: program_inputs(name, data, mesh) for name in losses}
    ref = losses["one device"](*args["one device"])
    errors = {name: rel_err(ref, fn(*args[name])) for name, fn in losses.items() if name != "one device"}
    loss_ms = median_ms(losses, args, rounds)

    host, obs = Callbacks(), jnp.ones((envs, OBS), jnp.float32)
    rep = NamedSharding(mesh, P())
    rollouts = {
        "one device": jax.jit(rollout_program(host, steps, None)),
        "replicated, callback on device 0": jax.jit(
            rollout_program(host, steps, SingleDeviceSharding(jax.devices()[0])),
            in_shardings=rep,
            out_shardings=rep,
        ),
    }
    rollout_args = {"one device": (obs,), "replicated, callback on device 0": (jax.device_put(obs, rep),)}
    calls = {}
    for name, fn in rollouts.items():
        fn(*rollout_args[name]).block_until_ready()  # compile
        host.calls = 0
        fn(*rollout_args[name]).block_until_ready()
        calls[name] = host.calls
    rollout_ms = median_ms(rollouts, rollout_args, rounds)
    return {
        "machine": measure.machine(),
        "envs": envs,
        "steps": steps,
        "rounds": rounds,
        "p": P_ACT,
        "q": Q,
        "loss_ms": loss_ms,
        "loss_rel_err": errors,
        "rollout_ms": rollout_ms,
        "callbacks_per_rollout": calls,
        "ok": all(e < REL_TOL for e in errors.values()) and all(c == steps for c in calls.values()),
    }


def _positive(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: expected an integer >= 1")
    return int(text)


def _even(text: str) -> int:
    value = _positive(text)
    if value % 2:
        raise argparse.ArgumentTypeError(
            f"invalid value {text!r}: expected an even integer >= 2 (split over 2 devices)"
        )
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="bench_results/two_core_loss.json")
    parser.add_argument("--envs", type=_even, default=4)
    parser.add_argument("--steps", type=_positive, default=1000)
    parser.add_argument("--rounds", type=_positive, default=7)
    args = parser.parse_args()
    if jax.device_count() < 2:
        flags, found = os.environ["XLA_FLAGS"], jax.device_count()
        parser.error(f"invalid XLA_FLAGS {flags!r}: {found} JAX device (allowed: a count of 2 or more)")
    result = run(args.envs, args.steps, args.rounds)
    print(
        f"{args.envs} chains x {args.steps} steps, p = {P_ACT}, q = {Q}; median ms over {args.rounds} rounds"
    )
    base = result["loss_ms"]["one device"]
    for name, ms in result["loss_ms"].items():
        err = result["loss_rel_err"].get(name)
        note = "" if err is None else f"  rel err {err:.1e}"
        print(f"loss + gradient, {name:<22} {ms:8.1f} ms  {base / ms:5.2f}x{note}")
    base = result["rollout_ms"]["one device"]
    for name, ms in result["rollout_ms"].items():
        calls = result["callbacks_per_rollout"][name]
        per_step = 1e3 * (ms - base) / args.steps
        print(f"rollout, {name:<33} {ms:8.1f} ms  +{per_step:6.1f} us per step  {calls} callbacks")
    out = Path(args.out)
    measure.write_json_atomic(out, result)
    print(
        f"wrote {out}"
        + ("" if result["ok"] else "; a check FAILED (see loss_rel_err, callbacks_per_rollout)")
    )
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
