"""What ``python -m coherent_jax.evaluate`` runs once its input is checked: a run's policy
evaluated in our engine (`evaluate_run`), optionally beside Gymnasium's own env of the task
(`gymnasium_returns`) and with a video of the first episode (`coherent_jax.run.video`).
The command imports this module after choosing MuJoCo's headless renderer (``MUJOCO_GL``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from coherent_jax.agents.rollout import evaluation_metrics
from coherent_jax.config.checks import gymnasium_id
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.host_gym import host_pool
from coherent_jax.envs.native import NATIVE_TASKS
from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.registry import CLASSIC_IDS
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.policy.net import PolicyError, read_policy
from coherent_jax.run import tracking, video
from coherent_jax.run.runs import load_config
from coherent_jax.run.video_path import default_suffix

__all__ = ["PolicyError", "evaluate_run", "gymnasium_action_map", "gymnasium_returns"]


def gymnasium_action_map(env: str, space) -> ActionMap:
    """The `ActionMap` from the agent's action in [-1, 1] to the action Gymnasium's env of task
    ``env`` receives: the task's own map onto the action space ``space`` (a MuJoCo task's
    `ActionMap.of_task` onto the Box's bounds; a classic task's centre + a * half-width,
    as `coherent_jax.envs.classic` maps it). Calling it clips to [-1, 1] first."""
    gym_id = gymnasium_id(env)
    if gym_id in CLASSIC_IDS:
        return ActionMap.of_box(space)
    task = NATIVE_TASKS[gym_id]
    return ActionMap.of_task(task.scale_action, task.brax_scaling, np.stack([space.low, space.high], axis=-1))


def gymnasium_returns(policy, env: str, episode_length: int, episodes: int, seed: int):
    """Returns and lengths [episodes] of the policy's deterministic episodes in Gymnasium.

    One ``gymnasium.make(gym_id, max_episode_steps=episode_length)`` per episode, stepped
    in lockstep so that the policy runs once per step on the batch of observations. Each
    observation is cast to float32 (our observations' type) and passed through the
    run's normalisation inside `PolicyNet.mean_action`; the action is clipped to [-1, 1]
    and mapped onto Gymnasium's action space with the task's own map
    (`gymnasium_action_map`: centre + a * half-width), exactly what `VecEnv.step` and the
    task do in training;
    SAC's tanh-squashed mean is already in [-1, 1]. An episode ends where Gymnasium's
    ``terminated`` or ``truncated`` (its time limit, here the run's ``episode_length``)
    says. Episode i is reset with the i-th word of ``SeedSequence(seed)``, so ``seed``
    reproduces the episodes and different seeds give different ones.
    """
    gym_id = gymnasium_id(env)
    envs = [_make_quietly(gymnasium, gym_id, episode_length) for _ in range(episodes)]
    space = envs[0].action_space
    to_space = gymnasium_action_map(env, space)
    act = jax.jit(lambda p, o: to_space(p.mean_action(o)))
    seeds = np.random.SeedSequence(seed).generate_state(episodes)
    obs = np.stack([e.reset(seed=int(s))[0] for e, s in zip(envs, seeds, strict=True)])
    returns, lengths = np.zeros(episodes), np.zeros(episodes, np.int64)
    running = np.ones(episodes, bool)
    while running.any():
        actions = np.asarray(act(policy, jnp.asarray(obs, jnp.float32)), space.dtype)
        for i in np.flatnonzero(running):
            obs[i], reward, terminated, truncated, _ = envs[i].step(actions[i])
            returns[i] += reward
            lengths[i] += 1
            running[i] = not (terminated or truncated)
    for e in envs:
        e.close()
    return returns, lengths


def _make_quietly(gymnasium, gym_id: str, episode_length: int):
    """``gymnasium.make(gym_id, max_episode_steps=episode_length)`` without MuJoCo's compiler
    warnings (settotalmass is deprecated in half_cheetah.xml and humanoid.xml), which it
    prints and, with no handler set, appends to MUJOCO_LOG.TXT in the working directory."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        with quiet_stdio(force=True):
            return gymnasium.make(gym_id, max_episode_steps=episode_length)
    finally:
        mujoco.set_mju_user_warning(previous)


def evaluate_run(run_dir: Path, opts: Any, mirror_wandb: bool = True) -> dict[str, Any]:
    """Evaluates the policy of `run_dir` with `opts` (a `coherent_jax.evaluate.EvalConfig`);
    returns the figures (and the video path). ``mirror_wandb=False`` keeps the video off the
    run's W&B run (an export, which uses no network)."""
    cfg = load_config(run_dir)
    recorder = video.Recorder(opts.max_frames)
    if opts.video:
        eval_env = video.recording_env(
            cfg.env, opts.episodes, cfg.episode_length, recorder, cfg.physics, cfg.physics_threads
        )
    else:
        eval_env = VecEnv(cfg.env, opts.episodes, cfg.episode_length, cfg.physics, cfg.physics_threads)
    policy, origin = read_policy(run_dir, eval_env.observation_size, eval_env.action_size)
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
        # What stepped these episodes: a Gymnasium env's own step() on the host, else our VecEnv
        # ("physics" names its engine: mjx, native, jax, ...) with Gymnasium's beside it on request.
        "engine": "gymnasium" if host_pool(eval_env) is not None else opts.engine,
        "physics": eval_env.physics,
    }
    if opts.engine == "gymnasium":
        returns, lengths = gymnasium_returns(policy, cfg.env, cfg.episode_length, opts.episodes, opts.seed)
        result.update(
            {
                "gymnasium_id": gymnasium_id(cfg.env),
                "gymnasium_version": gymnasium.__version__,
                "gymnasium_return_mean": float(returns.mean()),
                "gymnasium_return_std": float(returns.std()),
                "gymnasium_episode_length_mean": float(lengths.mean()),
            }
        )
    if opts.video:
        jax.effects_barrier()
        pool = host_pool(eval_env)
        if pool is not None:  # a Gymnasium env's own frames, at its own size
            frames = pool.frames
        else:
            model = video.mujoco_model_of(eval_env, cfg.env)
            frames = video.render_frames(model, recorder.qpos, opts.width, opts.height)
        stem = "final" if origin["iteration"] is None else f"it{origin['iteration']}"
        name = f"eval-{stem}-s{opts.seed}{default_suffix()}"
        path = Path(opts.video_path) if opts.video_path else run_dir / "videos" / name
        video.write_video(path, frames, fps=1.0 / eval_env.dt)
        result.update({"video": str(path), "frames": len(frames)})
        if cfg.wandb and mirror_wandb:  # the run's own W&B run (its id in the run directory) gets the video
            with tracking.session(run_dir):
                mirror = tracking.WandbRun.open(
                    run_dir, None, run_dir.name, init_timeout=cfg.wandb_init_timeout
                )
                mirror.video(path, step=None)
                mirror.finish()
    return result
