"""What ``python -m coherent_jax.evaluate`` runs once its input is checked: a run's policy
evaluated in our engine (`evaluate_run`), optionally beside Gymnasium's own env of the task
(`gymnasium_returns`) and with a video of the first episode. The command imports this module
after choosing MuJoCo's headless renderer (``MUJOCO_GL``).

Videos of evaluation episodes: record env 0's states inside the jitted evaluation, render
them with MuJoCo's offscreen renderer, and write an MP4 (with ``ffmpeg`` on the PATH) or a GIF
(the path and format: `coherent_jax.run.outputs.video_suffix`).

Recording is a host callback on the evaluation environment's step, so any trainer's
``evaluate`` is used unchanged and the video shows exactly the episodes whose returns
are reported. Rendering follows what Gymnasium's MuJoCo renderer does for its
locomotion tasks: a camera that tracks the agent's root body from the side at a
distance that fits the body, and a brighter headlight (the task models light the
scene from straight above, which leaves a side view dark).
"""

from __future__ import annotations

import copy
import os
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from PIL import Image

from coherent_jax.agents.rollout import evaluation_metrics
from coherent_jax.config.checks import gymnasium_id
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.gym_source import render_problem
from coherent_jax.envs.host_gym import host_pool
from coherent_jax.envs.jax_env import BraxInterfaceEnv, jax_env
from coherent_jax.envs.physics import NATIVE_TASKS, mujoco_model
from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.registry import CLASSIC_IDS, check_task
from coherent_jax.envs.user import load_user_task
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.policy.net import PolicyError, read_policy
from coherent_jax.run.checkpoint import load_config
from coherent_jax.run.outputs import WandbRun, video_suffix, wandb_session

__all__ = ["PolicyError", "evaluate_run", "gymnasium_action_map", "gymnasium_returns"]
# Camera as Gymnasium's locomotion tasks set it: from the side, a little above.
_AZIMUTH, _ELEVATION = 90.0, -20.0
# Distance from the tracked body, in units of the body's radius (its farthest geom from the root).
_DISTANCE_PER_RADIUS, _MIN_DISTANCE = 2.5, 1.5


def gymnasium_action_map(env: str, space) -> ActionMap:
    """The `ActionMap` from the agent's action in [-1, 1] to the action Gymnasium's env of task
    ``env`` receives: the task's own map onto the action space ``space`` (a MuJoCo task's
    `ActionMap.of_task` onto the Box's bounds; a classic task's centre + a * half-width,
    as `coherent_jax.envs.brax_env` maps it). Calling it clips to [-1, 1] first."""
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
    recorder = Recorder(opts.max_frames)
    if opts.video:
        eval_env = recording_env(
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
            model = mujoco_model_of(eval_env, cfg.env)
            frames = render_frames(model, recorder.qpos, opts.width, opts.height)
        stem = "final" if origin["iteration"] is None else f"it{origin['iteration']}"
        name = f"eval-{stem}-s{opts.seed}{video_suffix()}"
        path = Path(opts.video_path) if opts.video_path else run_dir / "videos" / name
        write_video(path, frames, fps=1.0 / eval_env.dt)
        result.update({"video": str(path), "frames": len(frames)})
        if cfg.wandb and mirror_wandb:  # the run's own W&B run (its id in the run directory) gets the video
            with wandb_session(run_dir):
                mirror = WandbRun.open(run_dir, None, run_dir.name, init_timeout=cfg.wandb_init_timeout)
                mirror.video(path, step=None)
                mirror.finish()
    return result


# --- video ----------------------------------------------------------------------------------------


class Recorder:
    """Host-side sink of (qpos, done) of evaluation env 0, step by step, until its episode ends."""

    def __init__(self, max_frames: int) -> None:
        self.qpos: list[Any] = []
        self.max_frames = max_frames
        self.ended = False

    def __call__(self, qpos: Any, done: Any) -> None:
        if not self.ended and len(self.qpos) < self.max_frames:
            self.qpos.append(np.array(qpos, dtype=np.float64))
        self.ended = self.ended or bool(done)


def video_problem(task: str) -> str | None:
    """Why a run of `task` cannot be filmed, or None: a JAX env of the user's that exposes no
    MuJoCo model, or a Gymnasium env that cannot render ``rgb_array``
    (`coherent_jax.envs.gym_source.render_problem`). Other tasks are checked by their kind."""
    backend = check_task(task).backend
    if backend == "jax-env" and jax_env(task).mj_model is None:
        return "this JAX environment exposes no MuJoCo model, mj_model or sys.mj_model"
    if backend == "gym":
        return render_problem(load_user_task(task).gym)
    return None


def recording_env(
    task: str,
    num_envs: int,
    episode_length: int,
    recorder: Recorder,
    physics: str = "auto",
    threads: int = 1,
):
    """A `VecEnv` whose ``step`` also sends env 0's generalized positions to `recorder`."""

    class RecordingVecEnv(VecEnv):
        def step(self, state, action):
            if host_pool(self) is not None:  # a Gymnasium env renders itself on the host
                return super().step(state, action)
            if hasattr(state.physics, "kin"):  # native MuJoCo physics
                qpos = state.physics.kin.qpos
            elif isinstance(self.env, BraxInterfaceEnv):  # a JAX env of the user's
                qpos = self.env.qpos(state.physics)
            else:
                physics = state.physics.pipeline_state
                qpos = physics.qpos if hasattr(physics, "qpos") else physics.q
            new_state, outcome = super().step(state, action)
            jax.debug.callback(recorder, qpos[0], outcome.done[0], ordered=True)
            return new_state, outcome

    env = RecordingVecEnv(task, num_envs, episode_length, physics, threads)
    pool = host_pool(env)
    if pool is not None:  # env 0's first episode, rendered by the env itself (``rgb_array``)
        pool.frames, pool.max_frames = [], recorder.max_frames
    return env


def mujoco_model_of(env: Any, task: str) -> Any:
    """The MuJoCo model behind an evaluation env (MJX's, or native physics' same MJCF)."""
    if isinstance(env.env, BraxInterfaceEnv):  # a JAX env of the user's: the model it exposes
        return env.env.mj_model
    if hasattr(env.env, "sys"):
        return env.env.sys.mj_model
    return mujoco_model(task)[0]


def lit_model(mj_model: Any) -> Any:
    """A copy of the model with a headlight bright enough for a side view."""
    model = copy.deepcopy(mj_model)
    model.vis.headlight.ambient[:] = 0.4
    model.vis.headlight.diffuse[:] = 0.7
    model.vis.headlight.specular[:] = 0.1
    model.vis.headlight.active = 1
    return model


def tracking_camera(model: Any, data: Any) -> Any:
    """A camera tracking body 1 (the agent's root) from the side, at a distance fitting the body."""
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, camera)
    if model.nbody < 2:
        return camera
    agent = model.geom_bodyid > 0
    reach = np.linalg.norm(data.geom_xpos[agent] - data.xpos[1], axis=1) + model.geom_rbound[agent]
    radius = float(reach.max()) if reach.size else 1.0
    camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    camera.trackbodyid = 1
    camera.distance = max(_MIN_DISTANCE, _DISTANCE_PER_RADIUS * radius)
    camera.azimuth, camera.elevation = _AZIMUTH, _ELEVATION
    return camera


def render_frames(mj_model: Any, qpos: Sequence[Any], width: int, height: int) -> list[Any]:
    """RGB frames [height, width, 3] of the model at each configuration in `qpos`."""
    model = lit_model(mj_model)
    data = mujoco.MjData(model)
    frames = []
    camera = None
    with mujoco.Renderer(model, height=height, width=width) as renderer:
        for q in qpos:
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            camera = camera or tracking_camera(model, data)  # sized on the first frame
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render().copy())
    return frames


def write_gif(path: Path, frames: Sequence[Any], fps: float) -> None:
    """An animated GIF of `frames`, written through a temporary file and a rename."""
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


def write_mp4(path: Path, frames: Sequence[Any], fps: float) -> None:
    """An H.264 MP4 of `frames` through ``ffmpeg`` (raw RGB on its stdin), then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width = frames[0].shape[:2]
    tmp = path.with_name(path.name + ".tmp.mp4")
    command = [
        shutil.which("ffmpeg") or "ffmpeg",
        "-y",
        "-loglevel",
        "error",
        "-f",
        "rawvideo",
        "-pix_fmt",
        "rgb24",
        "-s",
        f"{width}x{height}",
        "-r",
        f"{fps:.6g}",
        "-i",
        "-",
        # yuv420p needs even sizes; players outside ffmpeg need yuv420p.
        "-vf",
        "pad=ceil(iw/2)*2:ceil(ih/2)*2",
        "-pix_fmt",
        "yuv420p",
        "-c:v",
        "libx264",
        str(tmp),
    ]
    raw = np.ascontiguousarray(np.stack(frames), dtype=np.uint8).tobytes()
    proc = subprocess.run(command, input=raw, capture_output=True)
    if proc.returncode != 0 or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        tail = (proc.stderr.decode(errors="replace").strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"ffmpeg failed writing {path}: {tail}")
    os.replace(tmp, path)


def write_video(path: Path, frames: Sequence[Any], fps: float) -> None:
    """`write_mp4` for a ``.mp4`` path, `write_gif` otherwise."""
    if path.suffix.lower() == ".mp4":
        write_mp4(path, frames, fps)
    else:
        write_gif(path, frames, fps)
