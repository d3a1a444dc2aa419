"""What a first hour of runs still hit: W&B online (row 9), a resume without a checkpoint
(row 11), accelerators (row 15). Seconds each: no learning runs, no network, no home."""

import json
import re
import signal
import socket

import pytest

from coherent_jax.config import parse_overrides
from coherent_jax.envs.registry import PhysicsError, auto_physics, resolve_physics
from coherent_jax.run import outputs
from coherent_jax.run.checkpoint import write_config
from coherent_jax.run.launch import launch_train
from coherent_jax.run.loop_state import StopRequest
from coherent_jax.train import main

TINY = [
    "env=pointmass",
    "algo=a2c",
    "num_envs=2",
    "ppo.num_minibatches=1",
    "unroll_length=4",
    "eval_episodes=2",
    "episode_length=20",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "progress=false",
    "tensorboard=false",
]
FAKE_KEY = "0123456789abcdef0123456789abcdef01234567"  # the form of a W&B key, known to no server
W_AND_B_VARS = (
    "WANDB_MODE",
    "WANDB_API_KEY",
    "WANDB_IDENTITY_TOKEN_FILE",
    "WANDB_BASE_URL",
    "WANDB_CONFIG_DIR",
    "WANDB_CACHE_DIR",
    "WANDB_DATA_DIR",
    "WANDB_ARTIFACT_DIR",
    "WANDB_DIR",
    "WANDB_SILENT",
    "NETRC",
    "XDG_CACHE_HOME",
    "XDG_DATA_HOME",
    "XDG_CONFIG_HOME",
)


@pytest.fixture
def home(tmp_path, monkeypatch):
    """An empty home directory and no W&B settings of the user's: nothing found, nothing touched."""
    path = tmp_path / "home"
    path.mkdir()
    for name in W_AND_B_VARS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(path))
    return path


def _files(path):
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


def _closed_port() -> int:
    """A local port nothing listens on: a W&B server that never answers, without the network."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_row9_wandb_online_without_credentials_is_one_line_exit_2_before_the_run_dir(home, tmp_path, capsys):
    pytest.importorskip("wandb")
    env = {"HOME": str(home), "WANDB_MODE": "online"}
    assert outputs.wandb_credentials(env) is None
    # Where `wandb login` and the user's settings put a key are found, without asking a server.
    (home / ".netrc").write_text("machine api.wandb.ai\n  login user\n  password " + FAKE_KEY + "\n")
    assert outputs.wandb_credentials(env) == str(home / ".netrc")
    assert outputs.wandb_credentials({**env, "WANDB_BASE_URL": "https://wandb.example.org"}) is None
    (home / ".netrc").unlink()
    assert outputs.wandb_credentials({**env, "WANDB_API_KEY": FAKE_KEY}) == "WANDB_API_KEY"
    (home / ".config/wandb").mkdir(parents=True)
    (home / ".config/wandb/settings").write_text(f"[default]\napi_key = {FAKE_KEY}\n")
    assert outputs.wandb_credentials(env) == str(home / ".config/wandb/settings")
    (home / ".config/wandb/settings").unlink()

    run = tmp_path / "run"
    for mode, needle in (("online", "wandb login"), ("onlin", "allowed: offline, online")):
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("WANDB_MODE", mode)
            assert main([*TINY, "wandb=true", f"run_dir={run}"]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and err.startswith("error: ") and needle in err, err
        assert not run.exists()
    assert _files(home) == [".config", ".config/wandb"]  # only what this test made


def test_row9_wandb_server_that_does_not_answer_ends_in_one_line_within_the_timeout(
    home, tmp_path, monkeypatch, capsys
):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "online")
    monkeypatch.setenv("WANDB_API_KEY", FAKE_KEY)
    monkeypatch.setenv("WANDB_BASE_URL", f"http://127.0.0.1:{_closed_port()}")
    run = tmp_path / "new" / "run"
    assert main([*TINY, "wandb=true", "wandb_init_timeout=2", f"run_dir={run}"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "W&B could not start" in lines[0] and "wandb_init_timeout=2 s" in lines[0], err
    assert not (tmp_path / "new").exists()  # the directories this run made are gone: a retry may use them
    assert _files(home) == []
    assert parse_overrides(["wandb_init_timeout=5"]).wandb_init_timeout == 5
    with pytest.raises(Exception, match="wandb_init_timeout"):
        parse_overrides(["wandb_init_timeout=0"])


def test_row9_offline_wandb_writes_its_files_in_the_run_directory_only(home, tmp_path):
    pytest.importorskip("wandb")
    run = tmp_path / "run"
    run.mkdir()
    before = dict(__import__("os").environ)
    with outputs.mirrored([(run, {"env": "pointmass"}, "run")]) as mirrors:
        mirrors.runs[0].log({"train/loss": 0.5}, step=1)
        mirrors.summaries = [{"final_eval_return": 1.0}]
    assert _files(home) == []  # no ~/.cache/wandb, ~/.config/wandb, ~/.local/share/wandb
    assert list((run / "wandb").glob("offline-run-*"))
    assert list((run / "wandb" / "cache").rglob("*.log"))  # W&B's service log, here
    assert dict(__import__("os").environ) == before
    # The user's own settings win; online keeps the user's config directory (the login).
    env = outputs.wandb_environment(run, {"WANDB_CACHE_DIR": "/elsewhere"})
    assert "WANDB_CACHE_DIR" not in env and env["WANDB_CONFIG_DIR"] == str(run / "wandb" / "config")
    assert "WANDB_CONFIG_DIR" not in outputs.wandb_environment(run, {"WANDB_MODE": "online"})


def test_row11_resume_without_a_checkpoint_says_so_and_sets_the_rows_aside(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    cfg = parse_overrides([*TINY, f"run_dir={run}"])  # checkpoint_every=10: killed before the first
    write_config(run, cfg)
    rows = "".join(json.dumps({"iteration": i, "env_steps": 8 * i}) + "\n" for i in range(1, 8))
    (run / "metrics.jsonl").write_text(rows)
    (run / "metrics.jsonl.discarded-1").write_text("earlier\n")  # never overwritten

    stop = StopRequest()
    stop.signum = signal.SIGTERM  # stops before training: the resume's start, and no learning run
    launched = launch_train([f"resume={run}"], stop)
    assert launched.summary is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "resume found no checkpoint" in err and "starting from iteration 0" in err
    assert "7 rows" in err and "metrics.jsonl.discarded-2" in err, err
    assert (run / "metrics.jsonl.discarded-2").read_text() == rows
    assert (run / "metrics.jsonl.discarded-1").read_text() == "earlier\n"
    assert not (run / "metrics.jsonl").exists()

    # Nothing logged (killed during the compile): said as well, nothing to set aside.
    launch_train([f"resume={run}"], stop)
    err = capsys.readouterr().err
    assert "resume found no checkpoint" in err and "set aside" not in err
    assert sorted(p.name for p in run.glob("metrics.jsonl*")) == [
        "metrics.jsonl.discarded-1",
        "metrics.jsonl.discarded-2",
    ]


def test_row15_physics_auto_never_picks_the_host_callback_on_an_accelerator():
    assert auto_physics(True, "cpu") == "native"
    for backend in ("gpu", "cuda", "rocm", "tpu"):
        assert auto_physics(True, backend) == "mjx"
        assert auto_physics(False, backend) == "mjx"
    assert auto_physics(False, "cpu") == "mjx"
    for task in ("halfcheetah", "Hopper-v5", "brax-halfcheetah", "dmc-ball_in_cup"):
        assert resolve_physics(task, "auto", backend="gpu") == "mjx"
        assert resolve_physics(task, "native", backend="gpu") == "native"  # asked for: as given
    assert resolve_physics("halfcheetah", "auto", backend="cpu") == "native"
    assert resolve_physics("pointmass", "auto", backend="gpu") == "jax"
    with pytest.raises(PhysicsError, match=r"physics=auto on gpu .*'humanoid'.*allowed: physics=native"):
        resolve_physics("humanoid", "auto", backend="gpu")


def _custom_calls(physics: str) -> set[str]:
    """The custom-call targets of the lowered training iteration on `inverted_pendulum`."""
    import jax

    from coherent_jax.agents import make_trainer

    cfg = parse_overrides(
        [
            "env=inverted_pendulum",
            f"physics={physics}",
            "num_envs=1",
            "unroll_length=1",
            "episode_length=4",
            "eval_episodes=1",
            "policy_hidden=[2]",
            "value_hidden=[2]",
            "ppo.num_epochs=1",
            "ppo.num_minibatches=1",
        ]
    )
    trainer = make_trainer(cfg)
    assert trainer.env.physics == physics
    state = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    text = jax.jit(trainer.iteration).lower(state).as_text()
    return set(re.findall(r"custom_call @([\w.]+)", text))


@pytest.mark.slow
def test_row15_the_mjx_iteration_holds_no_host_callback_and_the_native_one_does():
    callback = re.compile(r"python.*callback|callback.*python|host_callback")
    native = _custom_calls("native")
    assert any(callback.search(t) for t in native), native  # the check sees a callback where there is one
    mjx = _custom_calls("mjx")
    assert not any(callback.search(t) for t in mjx), mjx
