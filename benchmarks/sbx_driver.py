"""SBX's SAC for the ``sbx`` suite, run by the SBX venv's Python (``python -I sbx_driver.py``).

The suite (`benchmarks.sbx`) starts this script in its own process and never imports it:
it needs SBX (``sbx-rl``), Stable-Baselines3, PyTorch and Gymnasium's MuJoCo tasks, which
live in the venv of ``benchmarks/sbx-requirements.txt``, not beside the package. It
imports nothing of this repository. ``-I`` keeps the script's folder off ``sys.path``, where
the suite's own ``sbx.py`` would hide SBX's package.

Protocol, one JSON object per line:

* stdin, first line: the settings (`benchmarks.sbx.sbx_settings`: the Gymnasium id, the
  number of envs, SAC's keyword arguments and ``warmup_iterations``). The driver builds
  ``sbx.SAC("MlpPolicy", make_vec_env(id, n_envs))`` as an SB3 user does (a
  ``DummyVecEnv`` of Gymnasium envs stepped one after the other in this process), runs the
  warm-up iterations (random actions until ``learning_starts``, the first compilations)
  and prints a line ``@sbx {...}``: versions, what SAC actually holds, setup and warm-up
  times.
* stdin, then: ``{"iterations": K}`` runs K more iterations and prints one ``@sbx``
  line of their times; ``{"quit": true}`` or the end of stdin ends the process.

One iteration is one pass of SB3's off-policy loop: ``collect_rollouts`` (``train_freq``
vector steps of ``n_envs`` envs, an action from the jitted actor each step, transitions
into SB3's NumPy replay buffer), then ``train`` (``gradient_steps`` updates in one jitted
``fori_loop`` on ``batch_size * gradient_steps`` transitions sampled on the host, its
losses read back to the host). A callback takes the time at each rollout's start and end
and at the end of ``learn``: collection is start to end, training end to the next start.
"""

from __future__ import annotations

import importlib.metadata
import json
import sys
import time

import flax.linen as nn
from sbx import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

MARK = "@sbx "  # the prefix of the driver's result lines on stdout (libraries may print too)
ACTIVATIONS = {"relu": nn.relu, "tanh": nn.tanh, "elu": nn.elu, "swish": nn.swish}
VERSIONS = ("sbx-rl", "stable_baselines3", "jax", "jaxlib", "flax", "optax", "tfp-nightly", "torch")
VERSIONS += ("gymnasium", "mujoco", "numpy")


class Clock(BaseCallback):
    """Times every iteration of ``learn``: (event, seconds) at each rollout's start and end
    and at the end of training."""

    def __init__(self) -> None:
        super().__init__()
        self.marks: list[tuple[str, float]] = []

    def _on_rollout_start(self) -> None:
        self.marks.append(("start", time.perf_counter()))

    def _on_rollout_end(self) -> None:
        self.marks.append(("collected", time.perf_counter()))

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        self.marks.append(("end", time.perf_counter()))

    def iterations(self) -> dict[str, list[float]]:
        """Each iteration's collection, training and whole seconds, in order."""
        collect, train = [], []
        for i, (event, t) in enumerate(self.marks):
            if event == "start":
                (_, t_collected), (_, t_next) = self.marks[i + 1], self.marks[i + 2]
                collect.append(t_collected - t)
                train.append(t_next - t_collected)
        whole = [c + u for c, u in zip(collect, train, strict=True)]
        return {"collect_s": collect, "train_s": train, "iteration_s": whole}


def build(settings: dict) -> SAC:
    """SBX's SAC on a ``DummyVecEnv`` of ``num_envs`` Gymnasium envs, with ``settings``' values."""
    sac = dict(settings["sac"])
    policy_kwargs = dict(sac.pop("policy_kwargs"))
    policy_kwargs["activation_fn"] = ACTIVATIONS[policy_kwargs["activation_fn"]]
    env = make_vec_env(
        settings["env_id"],
        n_envs=settings["num_envs"],
        seed=settings["seed"],
        env_kwargs={"max_episode_steps": settings["episode_length"]},
    )
    sac["train_freq"] = tuple(sac["train_freq"])
    return SAC("MlpPolicy", env, policy_kwargs=policy_kwargs, seed=settings["seed"], verbose=0, **sac)


def held(model: SAC) -> dict:
    """What the built SAC actually holds, read back from it (the suite checks it against its request)."""
    policy = model.policy
    return {
        "n_envs": model.n_envs,
        "env_steps_per_iteration": model.train_freq.frequency * model.n_envs,
        "train_freq": [model.train_freq.frequency, model.train_freq.unit.value],
        "gradient_steps": model.gradient_steps,
        "batch_size": model.batch_size,
        "buffer_size": model.replay_buffer.buffer_size * model.n_envs,
        "learning_starts": model.learning_starts,
        "learning_rate": float(model.lr_schedule(1)),
        "qf_learning_rate": float(model.qf_learning_rate),
        "gamma": model.gamma,
        "tau": model.tau,
        "policy_delay": model.policy_delay,
        "ent_coef": model.ent_coef_init,
        "target_entropy": float(model.target_entropy),
        "net_arch_pi": list(policy.net_arch_pi),
        "net_arch_qf": list(policy.net_arch_qf),
        "n_critics": policy.n_critics,
        "activation_fn": next((k for k, f in ACTIVATIONS.items() if f is policy.activation_fn), None),
        "vec_env": type(model.env).__name__,
        "max_episode_steps": model.env.envs[0].spec.max_episode_steps,
    }


def run(model: SAC, iterations: int) -> dict[str, list[float]]:
    """``iterations`` more iterations of SBX's ``learn``, timed by a `Clock`."""
    clock = Clock()
    steps = model.train_freq.frequency * model.n_envs
    model.learn(
        total_timesteps=iterations * steps,
        callback=clock,
        reset_num_timesteps=model.num_timesteps == 0,
        log_interval=10**9,
    )
    return clock.iterations()


def say(record: dict) -> None:
    print(MARK + json.dumps(record), flush=True)


def versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in VERSIONS:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def main() -> int:
    settings = json.loads(sys.stdin.readline())
    t0 = time.perf_counter()
    model = build(settings)
    setup_s = time.perf_counter() - t0
    warmup = run(model, settings["warmup_iterations"])
    say(
        {
            "ready": True,
            "versions": versions(),
            "held": held(model),
            "setup_s": setup_s,
            "warmup": warmup,
            "num_timesteps": model.num_timesteps,
            "updates_done": model._n_updates,
        }
    )
    for line in sys.stdin:
        command = json.loads(line)
        if command.get("quit"):
            break
        done = model._n_updates
        timed = run(model, int(command["iterations"]))
        say({**timed, "updates": model._n_updates - done, "num_timesteps": model.num_timesteps})
    model.env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
