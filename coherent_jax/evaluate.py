"""Evaluate a run's checkpoint: ``python -m coherent_jax.evaluate RUN_DIR episodes=10 video=true``.

Loads ``RUN_DIR/checkpoint.msgpack`` (verified as in `coherent_jax.runs`), runs
``episodes`` deterministic (mean-action) episodes in parallel with the trainer's own
``evaluate`` and prints the mean and standard deviation of their returns. With
``video=true`` it also renders the first episode (`coherent_jax.video`; headless:
``MUJOCO_GL=egl`` by default, or ``osmesa``) to
``RUN_DIR/videos/eval-it<iteration>-s<seed>.mp4`` (``.gif`` without ffmpeg) unless
``video_path`` is given. `pointmass` has no MuJoCo model and refuses ``video=true``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax import cli, video
from coherent_jax.config import ConfigError
from coherent_jax.runs import CHECKPOINT, CheckpointError, decode_checkpoint, load_config

KEYS: dict[str, cli.Key] = {
    "episodes": cli.Key(
        10, cli.int_at_least(1), "an integer >= 1", "deterministic episodes, run in parallel"
    ),
    "video": cli.Key(False, cli.boolean, "true or false", "render the first episode (MuJoCo tasks only)"),
    "seed": cli.Key(0, cli.int_at_least(0), "an integer >= 0", "PRNG seed of the evaluation episodes"),
    "video_path": cli.Key(
        "",
        video.check_path,
        video.PATH_ALLOWED,
        "where the video goes; default RUN_DIR/videos/eval-it<iteration>-s<seed>.mp4 (.gif without ffmpeg)",
    ),
    "width": cli.Key(320, cli.int_between(16, 640), "an integer in [16, 640]", "video width in pixels"),
    "height": cli.Key(240, cli.int_between(16, 480), "an integer in [16, 480]", "video height in pixels"),
    "max_frames": cli.Key(1000, cli.int_at_least(2), "an integer >= 2", "at most this many frames"),
}


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Settings of ``python -m coherent_jax.evaluate RUN_DIR [key=value ...]`` (defaults: `KEYS`)."""

    episodes: int
    video: bool
    seed: int
    video_path: str
    width: int
    height: int
    max_frames: int


def parse_eval_args(argv: Sequence[str]) -> tuple[Path, EvalConfig]:
    """``RUN_DIR`` then ``key=value`` settings; raises `ConfigError` in one line."""
    positional = [a for a in argv if "=" not in a]
    if len(positional) != 1:
        raise ConfigError(
            f"expected one run directory, got {len(positional)}: {positional!r} "
            "(usage: python -m coherent_jax.evaluate RUN_DIR [episodes=10] [video=true] ...)"
        )
    items = [a for a in argv if "=" in a]
    settings = cli.parse_command(items, KEYS, command="evaluate", config=False).settings
    return Path(positional[0]), EvalConfig(**settings)


def evaluate_run(run_dir: Path, opts: EvalConfig) -> dict[str, Any]:
    """Evaluates the checkpoint of `run_dir`; returns the figures (and the video path)."""
    import jax

    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv
    from coherent_jax.runs import restore_state

    cfg = load_config(run_dir)
    ckpt = decode_checkpoint(run_dir / CHECKPOINT, cfg)
    cfg = dataclasses.replace(cfg, eval_episodes=opts.episodes)
    recorder = video.Recorder(opts.max_frames)
    if opts.video:
        eval_env = video.recording_env(
            cfg.env, opts.episodes, cfg.episode_length, recorder, cfg.physics, cfg.physics_threads
        )
    else:
        eval_env = VecEnv(cfg.env, opts.episodes, cfg.episode_length, cfg.physics, cfg.physics_threads)
    trainer = make_trainer(cfg, eval_env=eval_env)
    template = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    state = restore_state(template, ckpt.state_bytes, run_dir / CHECKPOINT)
    metrics = jax.device_get(jax.jit(trainer.evaluate)(state, jax.random.PRNGKey(opts.seed)))
    result = {
        "run_dir": str(run_dir),
        "iteration": ckpt.iteration,
        "env_steps": ckpt.env_steps,
        "episodes": opts.episodes,
        "seed": opts.seed,
        "return_mean": float(metrics["eval/episode_return"]),
        "return_std": float(metrics["eval/episode_return_std"]),
        "episode_length_mean": float(metrics["eval/episode_length"]),
    }
    if opts.video:
        jax.effects_barrier()
        frames = video.render_frames(
            video.mujoco_model_of(eval_env, cfg.env), recorder.qpos, opts.width, opts.height
        )
        name = f"eval-it{ckpt.iteration}-s{opts.seed}{video.default_suffix()}"
        path = Path(opts.video_path) if opts.video_path else run_dir / "videos" / name
        video.write_video(path, frames, fps=1.0 / eval_env.dt)
        result.update({"video": str(path), "frames": len(frames)})
    return result


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print("usage: python -m coherent_jax.evaluate RUN_DIR [key=value ...]\n\noptions (key=default):")
        print("\n".join(cli.help_lines(KEYS)))
        return 0
    # Headless rendering; must be chosen before mujoco is first imported.
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        run_dir, opts = parse_eval_args(argv)
        if not run_dir.is_dir():
            raise ConfigError(
                f"invalid run directory {str(run_dir)!r}: not a directory (allowed: a run directory)"
            )
        cfg = load_config(run_dir)
        decode_checkpoint(run_dir / CHECKPOINT, cfg)
        from coherent_jax.envs.registry import TASKS

        if opts.video and TASKS[cfg.env].backend == "jax":
            raise ConfigError(
                f"invalid value for 'video': true with env={cfg.env} "
                "(allowed: false; this task has no MuJoCo model to render)"
            )
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return cli.EXIT_BAD_INPUT
    print(f"[coherent_jax] evaluating {run_dir} ({opts.episodes} episodes)", flush=True)
    result = evaluate_run(run_dir, opts)
    print(
        f"[coherent_jax] {cfg.env} {cfg.algo} explore={cfg.explore}, iteration {result['iteration']} "
        f"({result['env_steps']} env steps): return "
        f"{result['return_mean']:.2f} +- {result['return_std']:.2f} "
        f"(mean +- std over {opts.episodes} episodes, mean length {result['episode_length_mean']:.1f})",
        flush=True,
    )
    if opts.video:
        print(f"[coherent_jax] video: {result['video']} ({result['frames']} frames)", flush=True)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
