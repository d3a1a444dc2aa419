"""What a checkpoint costs: size, write time (encode + atomic write) and read time
(verify + restore) of the whole train state, for the configs given.

    python experiments/checkpoint_cost.py [OUT.json] [--repeats 5] -- env=halfcheetah [...]

Each config after ``--`` is one comma-separated list of overrides, e.g.
``env=halfcheetah,explore=coherent``. The state has the trainer's exact shapes
(traced from ``init``, filled with random numbers; nothing is compiled), and goes
through the code the train loop uses (`coherent_jax.run.checkpoint`). Prints one line per
config and writes the figures to OUT.json (default bench_results/checkpoint_cost.json).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from coherent_jax.agents import make_trainer
from coherent_jax.config import parse_overrides
from coherent_jax.run.checkpoint import CHECKPOINT, LoopState, decode_checkpoint, encode_checkpoint
from coherent_jax.run.devices import restore_state, state_to_bytes
from coherent_jax.run.rundir import atomic_write


def measure(overrides: list[str], repeats: int) -> dict:
    cfg = parse_overrides(overrides)
    shapes = jax.eval_shape(make_trainer(cfg).init, jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)

    def fill(s):
        if np.issubdtype(s.dtype, np.floating):
            return rng.standard_normal(s.shape).astype(s.dtype)
        return np.zeros(s.shape, s.dtype)

    state = jax.tree.map(fill, shapes)
    path = Path(tempfile.mkdtemp()) / CHECKPOINT
    writes, reads = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        blob = encode_checkpoint(cfg, 1, 1, LoopState(eval_key=[0, 0]), state_to_bytes(state))
        atomic_write(path, blob)
        writes.append(time.perf_counter() - t)
        t = time.perf_counter()
        restore_state(shapes, decode_checkpoint(path, cfg).state_bytes, path)
        reads.append(time.perf_counter() - t)
    return {
        "overrides": overrides,
        "arrays": len(jax.tree.leaves(shapes)),
        "bytes": len(blob),
        "write_ms_median": 1e3 * float(np.median(writes)),
        "read_ms_median": 1e3 * float(np.median(reads)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="bench_results/checkpoint_cost.json")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("configs", nargs="*", default=["env=halfcheetah", "env=halfcheetah,explore=coherent"])
    args = parser.parse_args()
    results = []
    for spec in args.configs:
        r = measure(spec.split(","), args.repeats)
        results.append(r)
        print(
            f"{spec:<40} {r['arrays']:>4} arrays  {r['bytes'] / 1e6:7.2f} MB  "
            f"write {r['write_ms_median']:6.1f} ms  read+verify+restore {r['read_ms_median']:6.1f} ms",
            flush=True,
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
