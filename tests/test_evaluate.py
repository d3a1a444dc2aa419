"""``python -m coherent_jax.evaluate``: returns from a checkpoint, a GIF whose frames move, bad input."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coherent_jax.config import parse_overrides, to_dict
from coherent_jax.evaluate import main, parse_eval_args
from coherent_jax.runs import CHECKPOINT, LoopState, atomic_write, encode_checkpoint, state_to_bytes

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
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("MUJOCO_GL", "egl")
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.evaluate", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )


POINTMASS = ["env=pointmass", "num_envs=2", "num_minibatches=1", "episode_length=20", "progress=false"]


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
    assert "+-" in out[-2]


def test_video_of_inverted_pendulum_has_moving_frames(tmp_path):
    """The GIF exists, its frames are not blank, and the pendulum moves between them."""
    from PIL import Image, ImageSequence

    run = make_zero_run(
        tmp_path / "run",
        ["env=inverted_pendulum", "num_envs=1", "num_minibatches=1", "episode_length=30", "progress=false"],
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
    ],
)
def test_bad_options_are_refused(tmp_path, args, text):
    from coherent_jax.config import ConfigError

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
