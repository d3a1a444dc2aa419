"""A Hugging Face Hub model folder of a trained run, written locally (no network).

    python -m coherent_jax.export RUN_DIR format=hub out=DIR
    hf upload USER/NAME DIR          # the Hub's own command-line tool, by the user

The folder holds ``README.md`` (the model card: YAML front matter with the Hub's
``library_name``, ``tags`` and ``model-index`` of the evaluation, then the task, algorithm,
strategy and its settings, mean ± std of ``evaluate`` over its episodes, the library's
version and commit, and the command that trained it), ``config.yaml`` (the run's),
``policy.msgpack`` and ``policy.json`` (the parameters and the action map, what
`coherent_jax.policy.load_policy` reads back), ``policy.onnx``, and ``replay.mp4`` (or
``.gif`` without ffmpeg) of an evaluation episode where the task renders (MuJoCo tasks; a
Gymnasium env that renders ``rgb_array``), else none, and `write_hub` says why. The folder
appears whole or not at all.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import yaml

import coherent_jax
from coherent_jax.config import Config, make_config, override_items
from coherent_jax.config.parse import overrides_of
from coherent_jax.envs.registry import check_task
from coherent_jax.policy.formats import write_onnx
from coherent_jax.policy.trained import META_FILE, POLICY_FILE, Policy, load_policy
from coherent_jax.run import rundir
from coherent_jax.run.evaluation import evaluate_run, video_problem
from coherent_jax.run.outputs import video_suffix

ONNX_FILE = "policy.onnx"


class HubEval(NamedTuple):
    """The evaluation settings `coherent_jax.run.evaluation.evaluate_run` reads."""

    episodes: int
    engine: str
    video: bool
    seed: int
    video_path: str
    width: int = 320
    height: int = 240
    max_frames: int = 1000


def training_command(cfg: Config) -> str:
    """``python -m coherent_jax.train`` with every setting of ``cfg`` that differs from the default."""
    base = dict(_flat(overrides_of(make_config({"algo": cfg.algo, "explore": cfg.explore}))))
    items = [i for i in override_items(overrides_of(cfg)) if i.split("=", 1)[0] in ("algo", "explore", "env")]
    for key, value in _flat(overrides_of(cfg)):
        if key not in ("algo", "explore", "env", "run_dir", "resume") and base.get(key) != value:
            items += override_items({key: value})
    return "python -m coherent_jax.train " + " ".join(items)


def _flat(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for k, v in d.items():
        if isinstance(v, dict):
            out += _flat(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def strategy_settings(cfg: Config) -> dict[str, Any]:
    """The config group of the strategy (``cfg.<explore>``), if it has one."""
    group = getattr(cfg, cfg.explore.replace("-", "_"), None)
    return dataclasses.asdict(group) if dataclasses.is_dataclass(group) else {}


def model_card(policy: Policy, figures: dict[str, Any], versions: dict[str, Any], command: str) -> str:
    """README.md of the folder: YAML front matter (the Hub's metadata), then the card."""
    cfg = policy.config
    mean, std, episodes = figures["return_mean"], figures["return_std"], figures["episodes"]
    front = {
        "library_name": "coherent_jax",
        "tags": ["reinforcement-learning", "jax", cfg.env, cfg.algo, cfg.explore],
        "model-index": [
            {
                "name": f"{cfg.algo}-{cfg.explore}-{cfg.env}",
                "results": [
                    {
                        "task": {"type": "reinforcement-learning", "name": "reinforcement-learning"},
                        "dataset": {"type": cfg.env, "name": cfg.env},
                        "metrics": [
                            {
                                "type": "mean_reward",
                                "value": f"{mean:.2f} +/- {std:.2f}",
                                "name": "mean_reward",
                            }
                        ],
                    }
                ],
            }
        ],
        "coherent_jax": {
            "task": cfg.env,
            "algorithm": cfg.algo,
            "strategy": cfg.explore,
            "strategy_settings": strategy_settings(cfg),
            "env_steps": policy.origin.get("env_steps"),
            "evaluation": {
                "return_mean": mean,
                "return_std": std,
                "episodes": episodes,
                "seed": figures["seed"],
            },
            "library_version": coherent_jax.__version__,
            "trained_at_commit": versions.get("git_commit"),
            "exported_at_commit": rundir.git_state().get("git_commit"),
            "training_command": command,
        },
    }
    settings = "\n".join(f"| `{k}` | `{v}` |" for k, v in strategy_settings(cfg).items()) or "| (none) | |"
    video = f"\n![an evaluation episode]({figures['video_name']})\n" if figures.get("video_name") else ""
    return f"""---
{yaml.safe_dump(front, sort_keys=False).rstrip()}
---

# {cfg.algo.upper()} with {cfg.explore} exploration on `{cfg.env}`

A policy trained with coherent_jax {coherent_jax.__version__} (commit `{versions.get("git_commit")}`),
{policy.origin.get("env_steps")} env steps.

**Evaluation** (`python -m coherent_jax.evaluate`, deterministic actions):
return **{mean:.2f} ± {std:.2f}** (mean ± std over {episodes} episodes, seed {figures["seed"]}).
{video}
## Strategy settings (`{cfg.explore}`)

| setting | value |
|---|---|
{settings}

## Use it

```python
import coherent_jax
policy = coherent_jax.load_policy("THIS_FOLDER")       # reads policy.msgpack + policy.json
action, state = policy.predict(obs)                     # in the env's action space
```

Without JAX: `{ONNX_FILE}` under onnxruntime, input `obs` [N, {policy.obs_size}] float32, output
`action` [N, {policy.action_size}] float32 (normalisation and action map included).

## Reproduce

```
{command}
```

`config.yaml` is the run's full configuration.
"""


def replay_problem(env: str) -> str | None:
    """None if the Hub folder can hold a replay of task `env`, else why not (one line): the
    pure-JAX tasks have no MuJoCo model, and a JAX or Gymnasium env of the user's may not render
    (`coherent_jax.run.evaluation.video_problem`, e.g. Pendulum-v1 without pygame)."""
    if check_task(env).backend == "jax":
        return "this task has no MuJoCo model to render"
    return video_problem(env)


def write_hub(
    run_dir: Path, out: Path, episodes: int = 10, seed: int = 0, replace: bool = False
) -> dict[str, Any]:
    """Writes the Hub folder of the run at ``run_dir`` as ``out``, which must not exist unless
    `replace`. The folder is built as a temporary sibling and renamed to ``out`` when complete, so
    a failure leaves no partial folder (and an existing ``out`` as it was). The figures returned
    hold ``replay_skipped``: why there is no replay video, or None."""
    out = Path(out)
    if out.exists() and not replace:
        raise FileExistsError(f"{out} exists")
    policy = load_policy(run_dir)
    skipped = replay_problem(policy.config.env)
    made = next((p for p in reversed([out.parent, *out.parent.parents]) if not p.exists()), None)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.parent / f".{out.name}.partial-{os.getpid()}"  # a sibling: the rename stays on its disk
    if partial.exists():  # left by an earlier process of this id that was killed
        shutil.rmtree(partial)
    partial.mkdir()
    try:
        figures = _write_folder(run_dir, partial, policy, episodes, seed, skipped is None)
        if out.exists():
            shutil.rmtree(out)
        partial.rename(out)
    except BaseException:
        shutil.rmtree(made or partial, ignore_errors=True)  # with the parent folders it created
        raise
    if figures["video_name"]:
        figures["video"] = str(out / figures["video_name"])
    return {**figures, "replay_skipped": skipped}


def _write_folder(
    run_dir: Path, out: Path, policy: Policy, episodes: int, seed: int, renders: bool
) -> dict[str, Any]:
    """The folder's files into the existing, empty ``out``; the evaluation's figures."""
    cfg = policy.config
    video_name = f"replay{video_suffix()}" if renders else ""
    opts = HubEval(episodes, "jax", renders, seed, str(out / video_name) if renders else "")
    figures = evaluate_run(run_dir, opts, mirror_wandb=False)
    figures["video_name"] = video_name
    (out / POLICY_FILE).write_bytes(policy.policy.to_bytes())
    meta = {"action_map": policy.action_map.to_dict(), "origin": policy.origin}
    (out / META_FILE).write_text(json.dumps(meta, indent=1) + "\n")
    shutil.copyfile(run_dir / "config.yaml", out / "config.yaml")
    write_onnx(policy, out / ONNX_FILE)
    versions_file = run_dir / "versions.json"
    versions = json.loads(versions_file.read_text()) if versions_file.is_file() else {}
    (out / "README.md").write_text(model_card(policy, figures, versions, training_command(cfg)))
    return figures
