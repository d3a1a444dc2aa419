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

from coherent_jax import video
from coherent_jax.config import ConfigError
from coherent_jax.runs import CHECKPOINT, CheckpointError, decode_checkpoint, load_config

EXIT_BAD_INPUT = 2


@dataclasses.dataclass
class EvalConfig:
    """Options of ``python -m coherent_jax.evaluate RUN_DIR [key=value ...]``."""

    episodes: int = 10
    video: bool = False
    seed: int = 0
    video_path: str = ""
    width: int = 320
    height: int = 240
    max_frames: int = 1000


EVAL_HELP = {
    "episodes": "deterministic episodes, run in parallel",
    "video": "render the first episode to a video (MuJoCo tasks only)",
    "seed": "PRNG seed of the evaluation episodes",
    "video_path": "a .mp4 (needs ffmpeg) or .gif path; default RUN_DIR/videos/eval-it<iteration>-s<seed>.*",
    "width": "video width in pixels (at most 640)",
    "height": "video height in pixels (at most 480)",
    "max_frames": "at most this many frames",
}


def parse_eval_args(argv: Sequence[str]) -> tuple[Path, EvalConfig]:
    """``RUN_DIR`` then ``key=value`` overrides; raises `ConfigError` in one line."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    positional = [a for a in argv if "=" not in a]
    overrides = [a for a in argv if "=" in a]
    if len(positional) != 1:
        raise ConfigError(
            f"expected one run directory, got {len(positional)}: {positional!r} "
            "(usage: python -m coherent_jax.evaluate RUN_DIR [episodes=10] [video=true] ...)"
        )
    known = {f.name for f in dataclasses.fields(EvalConfig)}
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key not in known:
            raise ConfigError(f"unknown key {key!r}; valid keys: {', '.join(sorted(known))}")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(EvalConfig()), OmegaConf.from_dotlist(overrides))
        cfg: EvalConfig = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        raise ConfigError(f"invalid value for {key!r}: {str(exc).splitlines()[0]}") from None
    checks = [
        ("episodes", cfg.episodes >= 1, "an integer >= 1"),
        ("seed", cfg.seed >= 0, "an integer >= 0"),
        ("width", 16 <= cfg.width <= 640, "an integer in [16, 640]"),
        ("height", 16 <= cfg.height <= 480, "an integer in [16, 480]"),
        ("max_frames", cfg.max_frames >= 2, "an integer >= 2"),
    ]
    for key, ok, allowed in checks:
        if not ok:
            raise ConfigError(f"invalid value for {key!r}: {getattr(cfg, key)!r} (allowed: {allowed})")
    if cfg.video_path:
        try:
            video.check_path(cfg.video_path)
        except ValueError:
            raise ConfigError(
                f"invalid value for 'video_path': {cfg.video_path!r} (allowed: {video.PATH_ALLOWED})"
            ) from None
    return Path(positional[0]), cfg


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
        for f in dataclasses.fields(EvalConfig):
            print(f"  {f.name}={f.default}".ljust(24) + f"  {EVAL_HELP[f.name]}")
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
        return EXIT_BAD_INPUT
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
