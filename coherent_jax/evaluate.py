"""Evaluate a run's policy: ``python -m coherent_jax.evaluate RUN_DIR episodes=10 video=true``.

``RUN_DIR`` is a training run's directory or one point of a sweep
(``runs/sweep-.../p003-beta=0.1-seed=1``). Its policy (`coherent_jax.policy.net.PolicyNet`) is
read from ``checkpoint.msgpack`` (verified as in `coherent_jax.run.checkpoint`), or from
``params.msgpack`` where there is no checkpoint, without building the training envs,
a trainer or a replay buffer. ``episodes`` deterministic (mean-action) episodes run in
parallel, as training evaluates, and the mean and standard deviation of their returns
are printed. With ``video=true`` it also renders the first episode
(`coherent_jax.run.evaluation`; headless: ``MUJOCO_GL=egl`` by default, or ``osmesa``) to
``RUN_DIR/videos/eval-it<iteration>-s<seed>.mp4`` (``.gif`` without ffmpeg) unless
``video_path`` is given (``video_path`` without ``video=true`` is refused); the physics
states come from inside the jitted evaluation, so the video shows exactly the episodes
whose returns are printed; a run trained with ``wandb=true`` also logs the video to its
W&B run (`coherent_jax.run.outputs`). The pure-JAX tasks (`pointmass`, the classic ones)
have no MuJoCo model and refuse ``video=true``. A sweep's root directory is refused with
the list of its points.

``engine=gymnasium`` also runs the policy in Gymnasium itself,
``gymnasium.make(<the task's Gymnasium id>)``, and prints Gymnasium's return beside
ours over the same number of episodes: the policy that training evaluates, acting on
each observation exactly as in training (`gymnasium_returns`). Only Gymnasium's own
tasks have a Gymnasium id: its MuJoCo tasks, which need ``gymnasium[mujoco]`` (the ``gym``
extra: ``pip install -e ".[gym]"``), and the classic ``mountain_car_continuous`` and
``pendulum`` (``MountainCarContinuous-v0``, ``Pendulum-v1``), which need Gymnasium alone.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from coherent_jax.compat import module_getattr
from coherent_jax.config import ConfigError, cli
from coherent_jax.config.checks import gymnasium_id
from coherent_jax.config.schema import MAX_SEED, SEED_ALLOWED
from coherent_jax.envs.registry import CLASSIC_IDS, check_task
from coherent_jax.exit_codes import EXIT_BAD_INPUT
from coherent_jax.run import outputs, rundir
from coherent_jax.run.checkpoint import CHECKPOINT, PARAMS, CheckpointError, decode_checkpoint, load_config

ENGINES = ("jax", "gymnasium")
#: ``gymnasium_returns`` lived here before the evaluation moved to `coherent_jax.run.evaluation`.
__getattr__ = module_getattr(__name__, {"gymnasium_returns": "coherent_jax.run.evaluation.gymnasium_returns"})
GYMNASIUM_EXTRA = 'pip install -e ".[gym]"'

KEYS: dict[str, cli.Key] = {
    "episodes": cli.Key(
        10, cli.int_at_least(1), "an integer >= 1", "deterministic episodes, run in parallel"
    ),
    "engine": cli.Key(
        "jax",
        cli.choice(ENGINES),
        " or ".join(ENGINES),
        "jax: our engine alone; gymnasium: also gymnasium.make(<the task's Gymnasium id>), side by side",
    ),
    "video": cli.Key(False, cli.boolean, "true or false", "render the first episode (MuJoCo tasks only)"),
    "seed": cli.Key(0, cli.int_between(0, MAX_SEED), SEED_ALLOWED, "PRNG seed of the evaluation episodes"),
    "video_path": cli.Key(
        "",
        outputs.check_video_path,
        outputs.VIDEO_PATH_ALLOWED,
        "where the video goes, only with video=true; default "
        "RUN_DIR/videos/eval-it<iteration>-s<seed>.mp4 (.gif without ffmpeg)",
    ),
    "width": cli.Key(320, cli.int_between(16, 640), "an integer in [16, 640]", "video width in pixels"),
    "height": cli.Key(240, cli.int_between(16, 480), "an integer in [16, 480]", "video height in pixels"),
    "max_frames": cli.Key(1000, cli.int_at_least(2), "an integer >= 2", "at most this many frames"),
}


# ``key=value`` with a plain key; a path such as a sweep point ``p003-beta=0.1-seed=1`` is not one.
_SETTING = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Settings of ``python -m coherent_jax.evaluate RUN_DIR [key=value ...]`` (defaults: `KEYS`)."""

    episodes: int
    engine: str
    video: bool
    seed: int
    video_path: str
    width: int
    height: int
    max_frames: int


def parse_eval_args(argv: Sequence[str]) -> tuple[Path, EvalConfig]:
    """``RUN_DIR`` then ``key=value`` settings; raises `ConfigError` in one line."""
    is_setting = [bool(_SETTING.match(a)) and not os.path.isdir(a) for a in argv]
    positional = [a for a, s in zip(argv, is_setting, strict=True) if not s]
    if len(positional) != 1:
        raise ConfigError(
            f"expected one run directory, got {len(positional)}: {positional!r} "
            "(usage: python -m coherent_jax.evaluate RUN_DIR [episodes=10] [video=true] ...)"
        )
    items = [a for a, s in zip(argv, is_setting, strict=True) if s]
    settings = cli.parse_command(items, KEYS, command="evaluate", config=False).settings
    if settings["video_path"] and not settings["video"]:
        raise ConfigError(
            f"invalid key 'video_path': {settings['video_path']!r} without video=true "
            "(allowed: video_path only with video=true)"
        )
    if settings["video"] and settings["engine"] != "jax":
        raise ConfigError(
            f"invalid value for 'engine': {settings['engine']!r} with video=true "
            "(allowed: jax; the video shows our engine's episodes)"
        )
    return Path(positional[0]), EvalConfig(**settings)


def check_gymnasium(env: str = "") -> None:
    """Raises `ConfigError` in one line when Gymnasium's env of task ``env`` cannot be made:
    a classic task needs Gymnasium, a MuJoCo task (or none named) ``gymnasium[mujoco]``."""
    classic = bool(env) and check_task(env).gymnasium_id in CLASSIC_IDS
    try:
        if classic:
            import gymnasium.envs.classic_control  # noqa: F401  # lazy: the check is whether it imports
        else:
            import gymnasium.envs.mujoco.mujoco_env  # noqa: F401  # lazy: needs gymnasium[mujoco], optional
    except Exception as exc:  # noqa: BLE001 - ImportError or gymnasium's DependencyNotInstalled
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        extra = "gymnasium" if classic else "gymnasium[mujoco]"
        raise ConfigError(
            f"engine=gymnasium needs {extra} ({reason}): install the gym extra, {GYMNASIUM_EXTRA}"
        ) from None


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
        rundir.check_one_run(run_dir, "evaluate")
        cfg = load_config(run_dir)
        if (run_dir / CHECKPOINT).is_file() or not (run_dir / PARAMS).is_file():
            decode_checkpoint(run_dir / CHECKPOINT, cfg)  # refuses a missing or broken one
        if opts.video and check_task(cfg.env).backend == "jax":
            raise ConfigError(
                f"invalid value for 'video': true with env={cfg.env} "
                "(allowed: false; this task has no MuJoCo model to render)"
            )
        if opts.video and check_task(cfg.env).backend in ("jax-env", "gym"):
            from coherent_jax.run.evaluation import video_problem  # lazy: JAX, MuJoCo; these envs only

            problem = video_problem(cfg.env)
            if problem:
                raise ConfigError(
                    f"invalid value for 'video': true with env={cfg.env} (allowed: false; {problem})"
                )
        if opts.engine == "gymnasium":
            gymnasium_id(cfg.env)
            check_gymnasium(cfg.env)
        if opts.video and cfg.wandb:
            outputs.wandb_preflight()
    except (ConfigError, CheckpointError, outputs.TrackingError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"[coherent_jax] evaluating {run_dir} ({opts.episodes} episodes)", flush=True)
    from coherent_jax.run import evaluation  # lazy: JAX and MuJoCo, after MUJOCO_GL is set

    try:
        result = evaluation.evaluate_run(run_dir, opts)
    except (CheckpointError, evaluation.PolicyError, outputs.TrackingError) as exc:
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
    if opts.engine == "gymnasium":
        print(
            f"[coherent_jax] Gymnasium {result['gymnasium_version']} {result['gymnasium_id']}: return "
            f"{result['gymnasium_return_mean']:.2f} +- {result['gymnasium_return_std']:.2f} "
            f"(mean +- std over {opts.episodes} episodes, "
            f"mean length {result['gymnasium_episode_length_mean']:.1f})",
            flush=True,
        )
    if opts.video:
        print(f"[coherent_jax] video: {result['video']} ({result['frames']} frames)", flush=True)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
