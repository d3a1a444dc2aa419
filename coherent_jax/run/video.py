"""Videos of evaluation episodes: record env 0's states inside the jitted evaluation, render
them with MuJoCo's offscreen renderer, and write an MP4 (with ``ffmpeg`` on the PATH) or a GIF.

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

import jax
import mujoco
import numpy as np
from PIL import Image

from coherent_jax.envs.gym_source import render_problem
from coherent_jax.envs.host_gym import host_pool
from coherent_jax.envs.jax_env import BraxInterfaceEnv, jax_env
from coherent_jax.envs.physics import mujoco_model
from coherent_jax.envs.registry import check_task
from coherent_jax.envs.user import load_user_task
from coherent_jax.envs.vec_env import VecEnv

# Camera as Gymnasium's locomotion tasks set it: from the side, a little above.
_AZIMUTH, _ELEVATION = 90.0, -20.0
# Distance from the tracked body, in units of the body's radius (its farthest geom from the root).
_DISTANCE_PER_RADIUS, _MIN_DISTANCE = 2.5, 1.5


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
