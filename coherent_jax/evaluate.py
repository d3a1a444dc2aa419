"""Evaluate a run's policy: ``python -m coherent_jax.evaluate RUN_DIR episodes=10 video=true``.

``RUN_DIR`` is a training run's directory or one point of a sweep
(``runs/sweep-.../p003-beta=0.1-seed=1``). Its policy (`coherent_jax.policy.Policy`) is
read from ``checkpoint.msgpack`` (verified as in `coherent_jax.runs`), or from
``params.msgpack`` where there is no checkpoint, without building the training envs,
a trainer or a replay buffer. ``episodes`` deterministic (mean-action) episodes run in
parallel, as training evaluates, and the mean and standard deviation of their returns
are printed. With
``video=true`` it also renders the first episode with MuJoCo's offscreen renderer
(headless: ``MUJOCO_GL=egl`` by default, or ``osmesa``) and writes an animated GIF
(``RUN_DIR/videos/eval-it<iteration>-s<seed>.gif`` unless ``video_path`` is given).

The physics states are taken from inside the jitted evaluation by a host callback
on the evaluation environment's step, so the video shows exactly the episodes whose
returns are printed.
`pointmass` has no MuJoCo model and refuses ``video=true``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import ConfigError
from coherent_jax.runs import CHECKPOINT, CheckpointError, decode_checkpoint, load_config

EXIT_BAD_INPUT = 2
# ``key=value`` with a plain key; a path such as a sweep point ``p003-beta=0.1-seed=1`` is not one.
_OVERRIDE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


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
    "video": "render the first episode to a GIF (MuJoCo tasks only)",
    "seed": "PRNG seed of the evaluation episodes",
    "video_path": "where to write the GIF; default RUN_DIR/videos/eval-it<iteration>-s<seed>.gif",
    "width": "video width in pixels (at most 640)",
    "height": "video height in pixels (at most 480)",
    "max_frames": "at most this many frames",
}


def parse_eval_args(argv: Sequence[str]) -> tuple[Path, EvalConfig]:
    """``RUN_DIR`` then ``key=value`` overrides; raises `ConfigError` in one line."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    is_override = [bool(_OVERRIDE.match(a)) and not os.path.isdir(a) for a in argv]
    positional = [a for a, o in zip(argv, is_override, strict=True) if not o]
    overrides = [a for a, o in zip(argv, is_override, strict=True) if o]
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
    return Path(positional[0]), cfg


class _Recorder:
    """Host-side sink of (qpos, done) of evaluation env 0, step by step, until its episode ends."""

    def __init__(self, max_frames: int) -> None:
        self.qpos: list[Any] = []
        self.max_frames = max_frames
        self.ended = False

    def __call__(self, qpos: Any, done: Any) -> None:
        import numpy as np

        if not self.ended and len(self.qpos) < self.max_frames:
            self.qpos.append(np.array(qpos, dtype=np.float64))
        self.ended = self.ended or bool(done)


def recording_env(
    task: str,
    num_envs: int,
    episode_length: int,
    recorder: _Recorder,
    physics: str = "auto",
    threads: int = 1,
):
    """A `VecEnv` whose ``step`` also sends env 0's generalized positions to `recorder`."""
    import jax

    from coherent_jax.envs.vec_env import VecEnv

    class RecordingVecEnv(VecEnv):
        def step(self, state, action):
            if hasattr(state.physics, "kin"):  # native MuJoCo physics
                qpos = state.physics.kin.qpos
            else:
                physics = state.physics.pipeline_state
                qpos = physics.qpos if hasattr(physics, "qpos") else physics.q
            new_state, outcome = super().step(state, action)
            jax.debug.callback(recorder, qpos[0], outcome.done[0], ordered=True)
            return new_state, outcome

    return RecordingVecEnv(task, num_envs, episode_length, physics, threads)


def render_frames(mj_model: Any, qpos: Sequence[Any], width: int, height: int) -> list[Any]:
    """RGB frames [height, width, 3] of the model at each configuration in `qpos`.

    The free camera is placed by MuJoCo's default for the model and follows the
    first body below the world, so a running agent stays in view.
    """
    import mujoco

    data = mujoco.MjData(mj_model)
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(mj_model, camera)
    track = 1 if mj_model.nbody > 1 else 0
    frames = []
    with mujoco.Renderer(mj_model, height=height, width=width) as renderer:
        for q in qpos:
            data.qpos[:] = q
            mujoco.mj_forward(mj_model, data)
            camera.lookat[:] = data.xpos[track]
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render().copy())
    return frames


def write_gif(path: Path, frames: Sequence[Any], fps: float) -> None:
    """An animated GIF of `frames`, written through a temporary file and a rename."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    tmp = path.with_name(path.name + ".tmp")
    images[0].save(
        tmp,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=max(20, int(round(1000.0 / fps))),
        loop=0,
    )
    os.replace(tmp, path)


def evaluate_run(run_dir: Path, opts: EvalConfig) -> dict[str, Any]:
    """Evaluates the policy of `run_dir`; returns the figures (and the video path)."""
    import jax

    from coherent_jax.envs.vec_env import VecEnv
    from coherent_jax.policy import load_policy
    from coherent_jax.rollout import evaluation_metrics

    cfg = load_config(run_dir)
    recorder = _Recorder(opts.max_frames)
    if opts.video:
        eval_env = recording_env(
            cfg.env, opts.episodes, cfg.episode_length, recorder, cfg.physics, cfg.physics_threads
        )
    else:
        eval_env = VecEnv(cfg.env, opts.episodes, cfg.episode_length, cfg.physics, cfg.physics_threads)
    policy, origin = load_policy(run_dir, eval_env.observation_size, eval_env.action_size)
    evaluate = jax.jit(lambda p, k: evaluation_metrics(eval_env, p.mean_action, k))
    metrics = jax.device_get(evaluate(policy, jax.random.PRNGKey(opts.seed)))
    result = {
        "run_dir": str(run_dir),
        "source": origin["source"],
        "iteration": origin["iteration"],
        "env_steps": origin["env_steps"],
        "episodes": opts.episodes,
        "seed": opts.seed,
        "return_mean": float(metrics["eval/episode_return"]),
        "return_std": float(metrics["eval/episode_return_std"]),
        "episode_length_mean": float(metrics["eval/episode_length"]),
    }
    if opts.video:
        jax.effects_barrier()
        if hasattr(eval_env.env, "sys"):
            mj_model = eval_env.env.sys.mj_model
        else:  # native physics: the same MJCF, with the task's solver options
            from coherent_jax.envs.native import mujoco_model

            mj_model = mujoco_model(cfg.env)[0]
        frames = render_frames(mj_model, recorder.qpos, opts.width, opts.height)
        stem = "final" if origin["iteration"] is None else f"it{origin['iteration']}"
        default = run_dir / "videos" / f"eval-{stem}-s{opts.seed}.gif"
        path = Path(opts.video_path) if opts.video_path else default
        write_gif(path, frames, fps=1.0 / eval_env.dt)
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
    from coherent_jax.policy import PARAMS, PolicyError

    try:
        run_dir, opts = parse_eval_args(argv)
        if not run_dir.is_dir():
            raise ConfigError(
                f"invalid run directory {str(run_dir)!r}: not a directory (allowed: a run directory)"
            )
        cfg = load_config(run_dir)
        if (run_dir / CHECKPOINT).is_file() or not (run_dir / PARAMS).is_file():
            decode_checkpoint(run_dir / CHECKPOINT, cfg)  # refuses a missing or broken one
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
    try:
        result = evaluate_run(run_dir, opts)
    except (CheckpointError, PolicyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    when = (
        f"{result['source']}"
        if result["iteration"] is None
        else f"iteration {result['iteration']} ({result['env_steps']} env steps)"
    )
    print(
        f"[coherent_jax] {cfg.env} {cfg.algo} explore={cfg.explore}, {when}: return "
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
