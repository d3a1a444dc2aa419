"""Short reference runs of every (algorithm, strategy) pair, to show a refactoring leaves training unchanged.

    PYTHONPATH=. python experiments/bit_identity.py record REF.json     # before the change
    PYTHONPATH=. python experiments/bit_identity.py check REF.json      # after: exit 1 on any difference
    PYTHONPATH=. python experiments/bit_identity.py compare REF.json NEW.json   # two recordings

Each run builds its trainer in-process on ``pointmass`` with small settings, starts it
from the keys a real run uses (`coherent_jax.run.loop.run_keys`), runs a few jitted
iterations and one deterministic evaluation, and records every metric of every
iteration plus a digest of the final parameters, as exact float32 bit patterns (a
NaN is a bit pattern too), so "identical" means bit for bit, not within a tolerance.
``check`` runs the same configurations and compares; ``RUNS=name,name`` limits both to
some of them. ``record`` saves after every run and keeps the runs already in its file,
so an interrupted recording resumes where it stopped.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time

import jax
import numpy as np

from coherent_jax import strategies
from coherent_jax.agents import make_trainer
from coherent_jax.config import parse_overrides
from coherent_jax.run.loop import run_keys

ON_POLICY = [
    "env=pointmass",
    "num_envs=8",
    "unroll_length=16",
    "episode_length=40",
    "ppo.num_epochs=2",
    "ppo.num_minibatches=2",
    "policy_hidden=[16,16]",
    "value_hidden=[16,16]",
    "eval_episodes=4",
]
SAC = [
    "env=pointmass",
    "algo=sac",
    "num_envs=4",
    "unroll_length=16",
    "episode_length=40",
    "policy_hidden=[16,16]",
    "value_hidden=[16,16]",
    "sac.warmup_steps=64",
    "sac.utd_ratio=0.25",
    "sac.batch_size=32",
    "sac.buffer_size=1024",
    "eval_episodes=4",
]
# Coherent's inference and gradient forms, which run the same classes: checked on top of
# the registry's strategies and variants.
COHERENT_FORMS = {
    "coherent_filter": ["explore=coherent", "coherent.inference=filter"],
    "coherent_episode": ["explore=coherent", "coherent.gradient=episode"],
    "coherent_stored": ["explore=coherent", "coherent.gradient=stored"],
}
# Every strategy and variant of the registry (a run's name: its own, "-" as "_"), then the forms.
STRATEGIES = {
    **{name.replace("-", "_"): list(strategies.overrides(name)) for name in strategies.on_policy_names()},
    **COHERENT_FORMS,
}
RUNS: dict[str, list[str]] = {}
for _algo in strategies.ON_POLICY:
    for _name, _extra in STRATEGIES.items():
        RUNS[f"{_algo}-{_name}"] = [*ON_POLICY, f"algo={_algo}", *_extra]
for _name in (n for n in strategies.EXPLORES if "sac" in strategies.SUPPORTED_ALGOS[n]):
    RUNS[f"sac-{_name}"] = [*SAC, *STRATEGIES[_name]]
ITERATIONS = {"sac": 6}  # SAC: two warm-up iterations, then updates and sigma adaptation
DEFAULT_ITERATIONS = 3


def _bits(x) -> list[int]:
    return np.asarray(x, np.float32).reshape(-1).view(np.uint32).tolist()


def _digest(tree) -> str:
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        h.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return h.hexdigest()


def run_one(overrides: list[str]) -> dict:
    cfg = parse_overrides(overrides)
    trainer = make_trainer(cfg)
    key, init_key = run_keys(cfg.seed)
    state = jax.jit(trainer.init)(init_key)
    iteration = jax.jit(trainer.iteration)
    rows = []
    for _ in range(ITERATIONS.get(cfg.algo, DEFAULT_ITERATIONS)):
        state, metrics = iteration(state)
        rows.append({k: _bits(v) for k, v in sorted(jax.device_get(metrics).items())})
    key, eval_key = jax.random.split(key)
    evaluation = jax.device_get(jax.jit(trainer.evaluate)(state, eval_key))
    return {
        "metrics": rows,
        "eval": {k: _bits(v) for k, v in sorted(evaluation.items())},
        "params": _digest(trainer.export_params(state)),
        "state": _digest(state),
    }


def compare(reference: dict, results: dict) -> list[str]:
    """Names of the runs of ``results`` that differ from (or are missing in) ``reference``."""
    return [name for name, result in results.items() if reference.get(name) != result]


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "compare":
        reference, results = (json.loads(open(p).read()) for p in argv[1:])
        failed = compare(reference, results)
        print(f"{len(results) - len(failed)} of {len(results)} runs bit-identical", end="")
        print(f"; different or missing: {failed}" if failed else "")
        return 1 if failed else 0
    if len(argv) != 2 or argv[0] not in ("record", "check"):
        print(__doc__)
        return 2
    mode, path = argv
    names = os.environ.get("RUNS", "").split(",") if os.environ.get("RUNS") else list(RUNS)
    if mode == "check":
        reference = json.loads(open(path).read())
        results = {}
    else:
        reference = {}
        results = json.loads(open(path).read()) if os.path.exists(path) else {}
    failed = []
    for name in names:
        if name in results:
            continue
        start = time.time()
        results[name] = run_one(RUNS[name])
        status = ""
        if mode == "check":
            status = "identical" if results[name] == reference.get(name) else "DIFFERENT"
            failed += [name] if status == "DIFFERENT" else []
        else:
            with open(path + ".tmp", "w") as f:
                json.dump(results, f)
            os.replace(path + ".tmp", path)
        print(f"{name:24s} {time.time() - start:6.1f} s {status}", flush=True)
    if mode == "record":
        print(f"{len(results)} runs recorded in {path}")
        return 0
    summary = f"{len(names) - len(failed)} of {len(names)} runs bit-identical"
    print(summary + (f"; different: {failed}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
