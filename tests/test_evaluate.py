"""``python -m coherent_jax.evaluate``: returns from a checkpoint, a GIF whose frames move, bad input."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import child_env

from coherent_jax.config import parse_overrides, to_dict
from coherent_jax.evaluate import main, parse_eval_args
from coherent_jax.run.checkpoint import CHECKPOINT, LoopState, encode_checkpoint
from coherent_jax.run.devices import state_to_bytes
from coherent_jax.run.rundir import atomic_write

ROOT = Path(__file__).resolve().parents[1]


def make_run(path: Path, overrides: list[str]) -> Path:
    """A run directory holding the checkpoint of a freshly initialised trainer (no training)."""
    import jax
    from omegaconf import OmegaConf

    from coherent_jax.agents import make_trainer

    cfg = parse_overrides(overrides)
    trainer = make_trainer(cfg)
    state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
    path.mkdir()
    atomic_write(path / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
    state_bytes = state_to_bytes(state)
    blob = encode_checkpoint(cfg, 0, 0, LoopState(eval_key=[0, 0]), state_bytes)
    atomic_write(path / CHECKPOINT, blob)
    return path


def make_zero_run(path: Path, overrides: list[str]) -> Path:
    """A run directory whose checkpoint holds a zero-filled state of the trainer's shape.

    Zero policy weights give zero actions, so a MuJoCo task still moves under its own
    dynamics; building the state by tracing ``init`` (no compile of an MJX reset)
    keeps the video test cheap.
    """
    import jax
    import numpy as np
    from omegaconf import OmegaConf

    from coherent_jax.agents import make_trainer

    cfg = parse_overrides(overrides)
    shapes = jax.eval_shape(make_trainer(cfg).init, jax.random.PRNGKey(0))
    state = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes)
    path.mkdir()
    atomic_write(path / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
    atomic_write(
        path / CHECKPOINT, encode_checkpoint(cfg, 0, 0, LoopState(eval_key=[0, 0]), state_to_bytes(state))
    )
    return path


def make_fake_run(path: Path, overrides: list[str]) -> Path:
    """A run directory whose checkpoint verifies but holds no restorable state (no compile).

    Enough for every refusal that happens before the state is restored.
    """
    from omegaconf import OmegaConf

    cfg = parse_overrides(overrides)
    path.mkdir()
    atomic_write(path / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
    atomic_write(path / CHECKPOINT, encode_checkpoint(cfg, 0, 0, LoopState(eval_key=[0, 0]), b"\x80" * 300))
    return path


def run_cli(args, cwd):
    env = child_env()
    env.setdefault("MUJOCO_GL", "egl")
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.evaluate", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )


POINTMASS = ["env=pointmass", "num_envs=2", "ppo.num_minibatches=1", "episode_length=20", "progress=false"]


def test_evaluate_prints_mean_and_std_of_returns(tmp_path, capsys):
    run = make_run(tmp_path / "run", POINTMASS)
    assert main([str(run), "episodes=6", "seed=3"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    result = json.loads(out[-1])
    assert result["episodes"] == 6 and result["iteration"] == 0
    # pointmass rewards are negative distances: 20 steps give a finite negative return.
    assert np.isfinite(result["return_mean"]) and result["return_mean"] < 0
    assert result["return_std"] > 0  # six episodes from different starts and goals
    assert result["episode_length_mean"] == 20
    assert (result["engine"], result["physics"]) == ("jax", "jax")  # our VecEnv, a pure-JAX task
    assert "+-" in out[-2]


def test_video_of_inverted_pendulum_has_moving_frames(tmp_path):
    """The GIF exists, its frames are not blank, and the pendulum moves between them."""
    from PIL import Image, ImageSequence

    run = make_zero_run(
        tmp_path / "run",
        [
            "env=inverted_pendulum",
            "num_envs=1",
            "ppo.num_minibatches=1",
            "episode_length=30",
            "progress=false",
        ],
    )
    video = tmp_path / "out.gif"
    proc = run_cli(
        [str(run), "episodes=2", "video=true", f"video_path={video}", "width=96", "height=72"], tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["video"] == str(video) and result["frames"] >= 2
    frames = [
        np.asarray(f.convert("RGB"), dtype=np.float64) for f in ImageSequence.Iterator(Image.open(video))
    ]
    assert len(frames) == result["frames"]
    assert frames[0].shape == (72, 96, 3)
    assert all(f.std() > 5.0 for f in frames), "a blank frame"
    assert np.abs(frames[0] - frames[-1]).mean() > 0.1, "first and last frames are the same"


def test_video_for_pointmass_is_refused(tmp_path, capsys):
    run = make_fake_run(tmp_path / "run", POINTMASS)
    before = sorted(p.name for p in run.rglob("*"))
    assert main([str(run), "video=true"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'video'" in err[0] and "pointmass" in err[0]
    assert sorted(p.name for p in run.rglob("*")) == before


@pytest.mark.parametrize(
    "args,text",
    [
        (["episodes=0"], "'episodes'"),
        (["episodes=two"], "'episodes'"),
        (["frames=3"], "'frames'"),
        (["width=4096"], "'width'"),
        (["video"], "one run directory"),
        (["video_path=out.avi"], "'video_path'.*gif"),
        (["video_path={tmp}"], "'video_path'"),
    ],
)
def test_bad_options_are_refused(tmp_path, args, text):
    from coherent_jax.config import ConfigError

    args = [a.format(tmp=tmp_path) for a in args]
    with pytest.raises(ConfigError, match=text) as err:
        parse_eval_args([str(tmp_path), *args])
    assert "\n" not in str(err.value)


def test_missing_or_foreign_run_dir_or_broken_checkpoint_is_refused(tmp_path, capsys):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "not a directory" in capsys.readouterr().err
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    assert main([str(stranger)]) == 2
    assert "config.yaml" in capsys.readouterr().err
    run = make_fake_run(tmp_path / "run", POINTMASS)
    path = run / CHECKPOINT
    path.write_bytes(path.read_bytes()[:100])
    assert main([str(run)]) == 2
    assert "truncated" in capsys.readouterr().err
    assert len(path.read_bytes()) == 100


FRAMING = """
import importlib.util, json, os
import mujoco, numpy as np
from coherent_jax.run import evaluation

# Brax's halfcheetah MJCF, loaded without importing JAX (the test stays a few seconds).
brax_dir = importlib.util.find_spec("brax").submodule_search_locations[0]
xml = os.path.join(brax_dir, "envs", "assets", "half_cheetah.xml")
model = evaluation.lit_model(mujoco.MjModel.from_xml_path(xml))
data = mujoco.MjData(model)
data.qpos[0] = 25.0  # far from the start: a tracking camera keeps the body in view
mujoco.mj_forward(model, data)
camera = evaluation.tracking_camera(model, data)
with mujoco.Renderer(model, height=96, width=128) as renderer:
    renderer.update_scene(data, camera=camera)
    rgb = renderer.render().astype(float)
    renderer.enable_segmentation_rendering()
    renderer.update_scene(data, camera=camera)
    seg = renderer.render()
geoms = np.flatnonzero(model.geom_bodyid > 0)
agent = np.isin(seg[..., 0], geoms) & (seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM)
print(json.dumps({"fraction": float(agent.mean()), "brightness": float(rgb[agent].mean())}))
"""


def test_video_frames_the_body_and_lights_it():
    """The agent fills a good part of the frame, also far from its start, and is lit.

    Measured with MuJoCo's segmentation rendering (which pixels show the agent's geoms).
    In this view the earlier free camera, placed for the whole scene, showed halfcheetah
    in 0.1% of the pixels (now 5.5%), and with the models' own lighting the body's pixels
    averaged 69 of 255 (now 110).
    """
    env = child_env()
    env.setdefault("MUJOCO_GL", "egl")
    proc = subprocess.run(
        [sys.executable, "-c", FRAMING], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen["fraction"] > 0.03, seen
    assert seen["brightness"] > 95.0, seen


def test_mp4_goes_through_ffmpeg_and_gif_without_it(tmp_path, monkeypatch):
    """With ffmpeg on the PATH the default is MP4, written from raw RGB frames on its stdin."""
    from coherent_jax.run import evaluation, outputs

    frames = [np.full((5, 7, 3), i * 40, dtype=np.uint8) for i in range(3)]
    cat = shutil.which("cat")  # the fake ffmpeg below runs where PATH holds nothing else
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert outputs.video_suffix() == ".gif"
    with pytest.raises(ValueError):
        outputs.check_video_path(str(tmp_path / "v.mp4"))
    evaluation.write_video(tmp_path / "v.gif", frames, fps=20.0)
    assert (tmp_path / "v.gif").read_bytes()[:6] == b"GIF89a"

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "ffmpeg"  # records its arguments and input, writes its output file
    fake.write_text(
        "#!/bin/sh\n"
        f'echo "$@" > {tmp_path}/args\n'
        f"{cat} > {tmp_path}/stdin\n"
        'for last; do :; done\necho mp4 > "$last"\n'
    )
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", str(bin_dir))
    assert outputs.video_suffix() == ".mp4"
    assert outputs.check_video_path(str(tmp_path / "out" / "v.mp4"))
    evaluation.write_video(tmp_path / "out" / "v.mp4", frames, fps=20.0)
    assert (tmp_path / "out" / "v.mp4").read_text() == "mp4\n"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["v.mp4"]  # no temporary file left
    assert "-s 7x5" in (tmp_path / "args").read_text() and "rgb24" in (tmp_path / "args").read_text()
    assert (tmp_path / "stdin").read_bytes() == np.stack(frames).tobytes()


# ------------------------------------------------- the policy, restored without a trainer


def random_state(trainer, seed=0):
    """A train state of the trainer's shapes with random parameters and observation statistics
    (the rest zeros), built without compiling anything: restoring the wrong leaves or
    skipping the normalisation would show."""
    import jax
    import numpy as np

    from coherent_jax.networks import RunningStats

    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    state = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes)
    params = jax.tree.map(lambda s: rng.normal(0.0, 0.3, s.shape).astype(s.dtype), shapes.params)
    size = shapes.obs_stats.mean.shape[0]
    stats = RunningStats(
        mean=rng.normal(size=size).astype(np.float32),
        var=np.exp(rng.normal(size=size)).astype(np.float32),
        count=np.float32(7.0),
    )
    return state.replace(params=params, obs_stats=stats)


def write_run(path: Path, cfg, trainer, state, checkpoint=True, params=True) -> Path:
    """A run directory as training writes it: config, checkpoint and/or params.msgpack."""
    import jax
    from flax import serialization
    from omegaconf import OmegaConf

    path.mkdir(parents=True)
    atomic_write(path / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
    if checkpoint:
        blob = encode_checkpoint(cfg, 3, 96, LoopState(eval_key=[0, 0]), state_to_bytes(state))
        atomic_write(path / CHECKPOINT, blob)
    if params:
        exported = jax.device_get(trainer.export_params(state))
        atomic_write(path / "params.msgpack", serialization.to_bytes(exported))
    return path


@pytest.mark.parametrize(
    "overrides",
    [
        ["algo=ppo", "explore=coherent"],
        ["algo=sac", "explore=psne", "sac.buffer_size=64", "policy_hidden=[16,16]", "value_hidden=[16,16]"],
    ],
    ids=["ppo-coherent", "sac-psne"],
)
def test_policy_restored_without_a_trainer_acts_as_the_agent(tmp_path, monkeypatch, overrides):
    """From a checkpoint and from params.msgpack: the arrays the trainer exports, and the
    trainer's deterministic action, with no trainer or replay buffer built on the way; the
    serialised policy round-trips bit for bit."""
    import jax

    from coherent_jax import agents
    from coherent_jax.agents import replay
    from coherent_jax.agents.onpolicy import OnPolicyTrainer
    from coherent_jax.agents.sac import SACTrainer
    from coherent_jax.networks import normalize
    from coherent_jax.policy.net import PolicyNet, read_policy

    cfg = parse_overrides([*POINTMASS, *overrides])
    trainer = agents.make_trainer(cfg)
    state = random_state(trainer)
    exported = trainer.export_params(state)
    sizes = (trainer.env.observation_size, trainer.env.action_size)
    obs = jax.random.normal(jax.random.PRNGKey(9), (5, sizes[0]))
    x = normalize(state.obs_stats, obs, cfg.normalize_obs)  # SAC runs default to no normalisation
    if cfg.algo == "sac":
        policy_params, expected = exported["actor"], trainer.actor.mode(state.params.actor, x)
    else:
        policy_params, expected = exported["policy"], trainer.strategy.mean_action(state.params.policy, x)
    run = write_run(tmp_path / "run", cfg, trainer, state)

    def refuse(*args, **kwargs):
        raise AssertionError("restoring the policy built a trainer or a replay buffer")

    for target, name in [(OnPolicyTrainer, "__init__"), (SACTrainer, "__init__"), (replay, "replay_init")]:
        monkeypatch.setattr(target, name, refuse)
    monkeypatch.setattr("coherent_jax.agents.sac.replay_init", refuse)

    for source in ("checkpoint.msgpack", "params.msgpack"):
        policy, origin = read_policy(run, *sizes)
        assert origin["source"] == source
        for got, want in zip(
            jax.tree.leaves((policy.params, policy.obs_stats)),
            jax.tree.leaves((policy_params, exported["obs_stats"])),
            strict=True,
        ):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        np.testing.assert_array_equal(np.asarray(policy.mean_action(obs)), np.asarray(expected))
        (run / CHECKPOINT).unlink(missing_ok=True)

    again = PolicyNet.from_bytes(policy.to_bytes())
    np.testing.assert_array_equal(np.asarray(again.mean_action(obs)), np.asarray(expected))
    # The stochastic action differs from the mean action but stays near it.
    sampled = np.asarray(jax.jit(lambda p, k, o: p.sample(k, o))(policy, jax.random.PRNGKey(1), obs))
    assert sampled.shape == (5, sizes[1]) and not np.allclose(sampled, np.asarray(expected))


def test_a_sweep_point_directory_is_evaluated_from_its_parameters(tmp_path, capsys):
    """A sweep writes one run directory per point, named with its values (``p001-beta=0.1-seed=0``):
    such a path is the run directory, not a ``key=value`` option, and its evaluation returns
    what the trainer's own ``evaluate`` returns for the same parameters."""
    import jax

    from coherent_jax.agents import make_trainer

    cfg = parse_overrides([*POINTMASS, "explore=coherent", "coherent.beta=0.1", "eval_episodes=3"])
    trainer = make_trainer(cfg)
    state = random_state(trainer)
    expected = jax.device_get(jax.jit(trainer.evaluate)(state, jax.random.PRNGKey(4)))
    point = tmp_path / "sweep" / "p001-beta=0.1-seed=0"
    write_run(point, cfg, trainer, state, checkpoint=False)
    run_dir, opts = parse_eval_args([str(point), "episodes=3"])
    assert run_dir == point and opts.episodes == 3
    assert main([str(point), "episodes=3", "seed=4"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["source"] == "params.msgpack" and result["iteration"] is None
    np.testing.assert_allclose(result["return_mean"], expected["eval/episode_return"], rtol=1e-6)
    np.testing.assert_allclose(result["return_std"], expected["eval/episode_return_std"], rtol=1e-5)
