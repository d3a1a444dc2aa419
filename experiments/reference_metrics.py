"""Records short reference runs, or checks that two recordings log identical metrics.

    PYTHONPATH=CHECKOUT python experiments/reference_metrics.py record DIR
    python experiments/reference_metrics.py compare DIR_A DIR_B

``record`` runs a few cheap pointmass jobs through the command-line entry points
(PPO with action noise and with coherent exploration, SAC, a resumed-after-stop PPO
run and a small sweep) into ``DIR``. ``compare`` holds every ``metrics.jsonl`` under
``DIR_B`` to the one at the same relative path under ``DIR_A``: every value of every
row equal (``time_s`` aside), so a change of the host loop that alters any seed's
numbers fails. Exit status 0 when identical, 1 otherwise.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

POINTMASS = [
    "env=pointmass",
    "num_envs=8",
    "unroll_length=16",
    "ppo.num_minibatches=2",
    "eval_episodes=4",
    "episode_length=50",
    "eval_every=3",
    "progress=false",
    "tensorboard=false",
]
JOBS = {
    "ppo_action": ("train", [*POINTMASS, "total_steps=1280", "seed=1"]),
    "ppo_coherent": ("train", [*POINTMASS, "total_steps=1280", "explore=coherent", "seed=2"]),
    "a2c_psne": ("train", [*POINTMASS, "algo=a2c", "total_steps=640", "explore=psne", "seed=3"]),
    "sac_coherent": (
        "train",
        [
            *POINTMASS,
            "algo=sac",
            "explore=coherent",
            "total_steps=1024",
            "sac.warmup_steps=256",
            "sac.utd_ratio=0.25",
            "sac.batch_size=32",
            "policy_hidden=[32]",
            "value_hidden=[32]",
        ],
    ),
    "sweep": (
        "sweep",
        [*POINTMASS, "total_steps=640", "explore=coherent", "coherent.beta=[0.01,0.5]", "seeds=2"],
    ),
}


def record(out: Path) -> None:
    """Runs every job as ``python -m coherent_jax.<command>``, the checkout's code on ``PYTHONPATH``."""
    out.mkdir(parents=True, exist_ok=False)
    for name, (command, args) in JOBS.items():
        argv = [sys.executable, "-m", f"coherent_jax.{command}", *args, f"run_dir={out / name}"]
        status = subprocess.run(argv, check=False).returncode
        if status != 0:
            raise SystemExit(f"{name}: exit status {status}")


def rows(path: Path) -> list[dict]:
    return [
        {k: v for k, v in json.loads(line).items() if k != "time_s"} for line in path.read_text().splitlines()
    ]


def compare(a: Path, b: Path) -> int:
    files = sorted(p.relative_to(a) for p in a.rglob("metrics.jsonl"))
    if not files:
        print(f"no metrics.jsonl under {a}")
        return 1
    bad = 0
    for rel in files:
        if not (b / rel).is_file():
            print(f"missing: {rel}")
            bad += 1
        elif rows(a / rel) != rows(b / rel):
            print(f"differs: {rel}")
            bad += 1
    print(f"{len(files) - bad} of {len(files)} metrics files identical")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "record":
        record(Path(sys.argv[2]))
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(compare(Path(sys.argv[2]), Path(sys.argv[3])))
    else:
        print(__doc__.strip().split("\n\n")[1], file=sys.stderr)
        sys.exit(2)
