"""``preset=thesis`` (Spinning Up's defaults), its layering under the user's overrides, its
round trip through ``config.yaml``, and the keys it needs: a value function on its own
optimiser (``vf_lr``, ``vf_iters``), ``max_grad_norm=0`` and SAC's ``update_after``."""

import dataclasses
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import child_env

from coherent_jax.agents import losses, make_trainer
from coherent_jax.config import SWEEPABLE, ConfigError, help_text, parse_overrides
from coherent_jax.policy.net import read_policy
from coherent_jax.run.checkpoint import load_config, resume_config, write_config
from coherent_jax.run.rundir import read_metrics
from coherent_jax.run.sweep import parse_sweep
from coherent_jax.train import main

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "presets.md"

# The values docs/presets.md documents, with their Spinning Up sources there. Written out
# here, not read from coherent_jax.config.schema, so that a change to either shows.
_ON_POLICY = {
    "num_envs": 4,
    "unroll_length": 1000,
    "episode_length": 1000,
    "gamma": 0.99,
    "ppo.gae_lambda": 0.97,
    "lr": 3e-4,
    "ppo.vf_lr": 1e-3,
    "ppo.vf_iters": 80,
    "ppo.ent_coef": 0.0,
    "ppo.max_grad_norm": 0.0,
    "ppo.normalize_advantages": True,
    "normalize_obs": False,
    "ppo.normalize_rewards": False,
    "policy_hidden": [64, 64],
    "value_hidden": [64, 64],
    "activation": "tanh",
    "init_std": math.exp(-0.5),
    "coherent.episode_restart": False,
}
THESIS = {
    "ppo": {
        **_ON_POLICY,
        "ppo.clip_eps": 0.2,
        "ppo.num_epochs": 80,
        "ppo.num_minibatches": 1,
        "ppo.target_kl": 0.01,
    },
    "a2c": {**_ON_POLICY, "ppo.num_epochs": 1, "ppo.num_minibatches": 1},
    "sac": {
        "num_envs": 1,
        "unroll_length": 50,
        "episode_length": 1000,
        "sac.utd_ratio": 1.0,
        "lr": 1e-3,
        "gamma": 0.99,
        "sac.tau": 0.005,
        "sac.temperature": 0.2,
        "sac.auto_temperature": False,
        "sac.batch_size": 100,
        "sac.buffer_size": 1_000_000,
        "sac.warmup_steps": 10_000,
        "sac.update_after": 1_000,
        "policy_hidden": [256, 256],
        "value_hidden": [256, 256],
        "activation": "relu",
        "normalize_obs": False,
        "eval_every": 80,
        "eval_episodes": 10,
    },
}
TINY = [
    "env=pointmass",
    "num_envs=4",
    "unroll_length=8",
    "episode_length=20",
    "ppo.num_minibatches=2",
    "ppo.num_epochs=2",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "eval_episodes=2",
    "progress=false",
    "tensorboard=false",
]


def get(cfg, key):
    group, _, name = key.rpartition(".")
    return getattr(getattr(cfg, group) if group else cfg, name)


def shown(value) -> str:
    """A value as docs/presets.md writes it in ``key=value``."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return "[" + ",".join(map(str, value)) + "]"
    return str(value)


@pytest.mark.parametrize("algo", ["ppo", "a2c", "sac"])
def test_thesis_preset_resolves_to_the_documented_values(algo):
    cfg = parse_overrides(["env=halfcheetah", f"algo={algo}", "preset=thesis"])
    assert cfg.preset == "thesis"
    for key, value in THESIS[algo].items():
        assert get(cfg, key) == pytest.approx(value), key
    if algo == "sac":
        assert (cfg.steps_per_iteration, cfg.updates_per_iteration) == (50, 50)  # update_every=50
        assert cfg.coherent.integration == "mc"  # algo=sac's own default, which the preset leaves
        assert cfg.coherent.episode_restart is True
    else:
        assert cfg.steps_per_iteration == 4000  # steps_per_epoch


@pytest.mark.parametrize("algo", ["ppo", "a2c", "sac"])
def test_docs_give_every_value_of_the_preset(algo):
    doc = DOC.read_text()
    section = doc.split(f"## preset=thesis, algo={algo}")[1].split("\n## ")[0]
    for key, value in THESIS[algo].items():
        assert f"`{key}={shown(value)}`" in section, key


def test_no_preset_is_todays_config():
    assert parse_overrides(["preset="]) == parse_overrides([]) == parse_overrides(["preset=none"])
    assert parse_overrides([]).preset == ""
    assert parse_overrides(["algo=sac", "preset=null"]) == parse_overrides(["algo=sac"])


def test_user_overrides_beat_the_preset_and_the_preset_beats_algo_defaults():
    items = ["algo=sac", "lr=3e-3", "coherent.episode_restart=false", "num_envs=2"]
    for order in (["preset=thesis", *items], [*items, "preset=thesis"]):
        cfg = parse_overrides(order)
        assert (cfg.lr, cfg.num_envs, cfg.coherent.episode_restart) == (3e-3, 2, False)
        assert (cfg.sac.batch_size, cfg.sac.update_after) == (100, 1000)  # the preset's
        assert (cfg.total_steps, cfg.checkpoint_every) == (300_000, 200)  # algo=sac's, under the preset
    cfg = parse_overrides(
        ["preset=thesis", "ppo.vf_iters=10", "ppo.num_epochs=5", "coherent.episode_restart=true"]
    )
    assert (cfg.ppo.vf_iters, cfg.ppo.num_epochs, cfg.coherent.episode_restart, cfg.ppo.vf_lr) == (
        10,
        5,
        True,
        1e-3,
    )


def test_preset_round_trips_through_config_yaml_and_resume(tmp_path):
    cfg = parse_overrides(["env=pointmass", "preset=thesis", "lr=1e-4", f"run_dir={tmp_path}"])
    write_config(tmp_path, cfg)
    text = (tmp_path / "config.yaml").read_text()
    assert "preset: thesis" in text and "vf_iters: 80" in text and "lr: 0.0001" in text
    assert load_config(tmp_path) == cfg
    # The preset is not applied again over the stored config (its lr=1e-4 stays).
    for again in ([], ["preset=thesis"], ["algo=ppo", "preset=thesis"]):
        resumed, _ = resume_config(str(tmp_path), again)
        assert dataclasses.replace(resumed, resume="") == cfg
    with pytest.raises(ConfigError, match="'preset' with resume"):
        resume_config(str(tmp_path), ["preset=none"])


def _train_in(folder, *items):
    """``python -m coherent_jax.train ITEMS run_dir=FOLDER/run``, run in `folder`."""
    return subprocess.run(
        [sys.executable, "-m", "coherent_jax.train", *items, f"run_dir={folder / 'run'}"],
        cwd=folder,
        capture_output=True,
        text=True,
        env=child_env(),
        timeout=120,
    )


def test_unknown_preset_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError) as err:
        parse_overrides(["preset=spinningup"])
    assert str(err.value) == "invalid value for 'preset': 'spinningup' (allowed: thesis, fast_sac)"
    proc = _train_in(tmp_path, "preset=x")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: invalid value for 'preset': 'x' (allowed: thesis, fast_sac)"
    ]
    assert list(tmp_path.iterdir()) == []


def test_fast_sac_keeps_the_gradient_work_per_iteration_over_four_times_the_env_steps():
    """``preset=fast_sac``: 64 envs x 8 steps and 32 updates of 1,024 per iteration, where
    algo=sac's defaults take 8 x 16 steps and 128 updates of 256: the same transitions
    sampled per iteration, 4x the env steps, and so 1/4 of the gradient work per env step."""
    fast = parse_overrides(["algo=sac", "preset=fast_sac"])
    default = parse_overrides(["algo=sac"])
    assert (fast.num_envs, fast.unroll_length, fast.sac.batch_size) == (64, 8, 1024)
    assert (fast.steps_per_iteration, fast.updates_per_iteration) == (512, 32)
    assert (default.steps_per_iteration, default.updates_per_iteration) == (128, 128)
    samples = [c.updates_per_iteration * c.sac.batch_size for c in (fast, default)]
    assert samples[0] == samples[1]
    assert fast.steps_per_iteration == 4 * default.steps_per_iteration
    # What the preset leaves: the learner, the networks and algo=sac's other defaults.
    same = ("lr", "gamma", "policy_hidden", "value_hidden", "total_steps", "sac.tau", "sac.warmup_steps")
    assert all(get(fast, k) == get(default, k) for k in same)
    # The user's values win; every strategy that SAC takes runs under it.
    assert parse_overrides(["algo=sac", "preset=fast_sac", "num_envs=16"]).num_envs == 16
    for explore in ("action", "coherent", "psne", "gsde", "pink", "lattice"):
        assert parse_overrides(["algo=sac", "preset=fast_sac", f"explore={explore}"]).preset == "fast_sac"


def test_a_preset_without_values_for_the_algo_is_refused_in_one_line(tmp_path):
    for algo in ("ppo", "a2c"):
        with pytest.raises(ConfigError) as err:
            parse_overrides([f"algo={algo}", "preset=fast_sac"])
        allowed = f"a preset with values for algo={algo}: thesis"
        assert str(err.value) == f"invalid value for 'preset': 'fast_sac' (allowed: {allowed})"
    proc = _train_in(tmp_path, "preset=fast_sac")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "'preset': 'fast_sac'" in proc.stderr and "algo=ppo: thesis" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_help_lists_the_preset_per_algo():
    text = help_text()
    assert "preset=thesis:" in text
    for algo in ("ppo", "a2c", "sac"):
        line = next(ln for ln in text.splitlines() if ln.startswith(f"  with algo={algo}:"))
        for key in ("num_envs", "unroll_length", "lr"):
            assert f"{key}={shown(THESIS[algo][key])}" in line, (algo, key)
    assert (
        "ppo.vf_iters=80" in text
        and "sac.update_after=1000" in text
        and "coherent.episode_restart=false" in text
    )


def test_separate_value_keys_are_checked_together_and_vf_lr_is_sweepable():
    assert "ppo.vf_lr" in SWEEPABLE
    plan = parse_sweep(["env=pointmass", "preset=thesis", "ppo.vf_lr=[0.001,0.0003]"])
    assert [(p.cfg.ppo.vf_lr, p.cfg.ppo.vf_iters) for p in plan.points] == [(1e-3, 80), (3e-4, 80)]
    with pytest.raises(ConfigError, match="'ppo.vf_iters'"):  # the joint loss has no vf_lr to vary
        parse_sweep(["env=pointmass", "ppo.vf_lr=[0.001,0.0003]"])
    with pytest.raises(ConfigError, match="'ppo.vf_iters'.*vf_lr=0.001"):
        parse_overrides(["ppo.vf_lr=1e-3"])
    with pytest.raises(ConfigError, match="'ppo.vf_iters'.*vf_lr=0"):
        parse_overrides(["ppo.vf_iters=4"])
    with pytest.raises(ConfigError, match="'ppo.max_grad_norm'"):
        parse_overrides(["ppo.max_grad_norm=-1"])


def run_iterations(overrides, iterations=2):
    return run_variants(overrides, [{}], iterations)[0]


def run_variants(overrides, variants, iterations=2):
    """(state, metrics) after `iterations` of one compiled trainer, for each dict of
    sweepable hyperparameters in `variants` (set in the state, as a sweep does)."""
    trainer = make_trainer(parse_overrides([*TINY, *overrides]))
    init, step = jax.jit(trainer.init), jax.jit(trainer.iteration)
    out = []
    for changes in variants:
        hparams = trainer.init_hparams()
        hparams = hparams.replace(**{k: jnp.asarray(v, jnp.float32) for k, v in changes.items()})
        state = init(jax.random.PRNGKey(0), hparams)
        for _ in range(iterations):
            state, metrics = step(state)
        out.append((state, metrics))
    return out


def leaves_equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def leaves_close(a, b) -> bool:
    """Equal up to float32 rounding (two different programs may round differently)."""
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return all(np.allclose(x, y, rtol=1e-5, atol=1e-6) for x, y in pairs)


@pytest.mark.slow
def test_separate_value_keeps_the_value_loss_out_of_the_policy_step():
    """With its own optimiser, vf_coef does not reach the policy (clipping on, so a shared
    global norm would couple them); with the joint loss it does."""
    vf_coefs = [{"vf_coef": 0.5}, {"vf_coef": 50.0}]
    (a, _), (b, _) = run_variants(["ppo.vf_lr=1e-3", "ppo.vf_iters=3", "ppo.max_grad_norm=0.05"], vf_coefs)
    assert leaves_equal(a.params.policy, b.params.policy)
    assert leaves_equal(a.params.value, b.params.value)
    (c, _), (d, _) = run_variants(["ppo.max_grad_norm=0.05"], vf_coefs)
    assert not leaves_equal(c.params.policy, d.params.policy)


@pytest.mark.slow
def test_value_takes_vf_iters_adam_steps_on_its_own_optimizer():
    state, metrics = run_iterations(["ppo.vf_lr=1e-3", "ppo.vf_iters=3"], iterations=2)
    # Adam's step counters: 3 value steps per iteration, the policy's applied steps apart.
    assert int(state.opt_state.value[-1].count) == 2 * 3  # (clip, Adam)
    assert int(state.opt_state.policy[-1].count) == 2 * 4  # num_epochs x num_minibatches
    assert np.isfinite(metrics["train/value_loss"]) and "train/value_grad_norm" in metrics
    assert float(state.hparams.vf_lr) == pytest.approx(1e-3)

    # The value steps against Adam at vf_lr written out (optax.adam, eps as the trainer's).
    trainer = make_trainer(
        parse_overrides([*TINY, "ppo.vf_lr=1e-2", "ppo.vf_iters=3", "ppo.max_grad_norm=0"])
    )
    init = trainer.init(jax.random.PRNGKey(1))
    obs = jax.random.normal(jax.random.PRNGKey(2), (8, 4, 6))
    targets = jax.random.normal(jax.random.PRNGKey(3), (8, 4))
    got, _, m = trainer._value_steps(init.params.value, init.opt_state.value, init.hparams, obs, targets)

    def loss(v):
        return losses.value_loss(trainer.value_net.apply(v, obs), targets)

    adam = optax.adam(1e-2, eps=1e-5)
    want, opt, first = init.params.value, adam.init(init.params.value), []
    for i in range(3):
        value, grads = jax.value_and_grad(loss)(want)
        first.append(value)
        if i == 2:
            two_steps = want
        updates, opt = adam.update(grads, opt, want)
        want = optax.apply_updates(want, updates)
    for g, w, t in zip(jax.tree.leaves(got), jax.tree.leaves(want), jax.tree.leaves(two_steps), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-7)
        assert not np.allclose(g, t)
    assert float(m["train/value_loss"]) == pytest.approx(float(jnp.mean(jnp.stack(first))), rel=1e-6)


@pytest.mark.slow
def test_max_grad_norm_zero_means_no_clipping():
    free, metrics = run_iterations(["ppo.max_grad_norm=0"])
    huge, _ = run_iterations(["ppo.max_grad_norm=1e30"])  # a clip that never binds
    tight, _ = run_iterations(["ppo.max_grad_norm=1e-3"])
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(free.params))
    assert leaves_close(free.params, huge.params)
    assert not leaves_close(free.params, tight.params)
    assert float(metrics["train/grad_norm"]) > 1e-3  # so the tight clip did bind


@pytest.mark.slow
def test_sac_updates_start_at_update_after_during_the_random_actions():
    trainer = make_trainer(
        parse_overrides(
            [
                *TINY,
                "algo=sac",
                "num_envs=1",
                "sac.warmup_steps=40",
                "sac.update_after=16",
                "sac.batch_size=8",
            ]
            + ["sac.buffer_size=64", "sac.utd_ratio=0.5"]
        )
    )
    state = jax.jit(trainer.init)(jax.random.PRNGKey(0))
    step = jax.jit(trainer.iteration)
    rows = []
    for _ in range(6):
        state, m = step(state)
        rows.append((int(state.env_steps), float(m["train/warmup"]), float(m["train/updates_applied"])))
    # 8 steps per iteration: random actions while fewer than 40 steps were done before
    # the iteration, updates (4 each) once 16 are.
    assert rows == [(8, 1, 0), (16, 1, 4), (24, 1, 4), (32, 1, 4), (40, 1, 4), (48, 0, 4)]


@pytest.mark.slow
def test_separate_value_run_resumes_to_the_uninterrupted_run(tmp_path):
    """The value's optimiser state is in the checkpoint: a run stopped and resumed equals
    one run straight through, and its policy loads from the checkpoint."""
    tiny = [o for o in TINY if not o.startswith("ppo.num_epochs=")]  # each key once
    args = [
        *tiny,
        "preset=thesis",
        "ppo.num_epochs=3",
        "ppo.vf_iters=4",
        "checkpoint_every=1",
        "eval_every=2",
    ]
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main([*args, "total_steps=96", f"run_dir={straight}"]) == 0
    assert main([*args, "total_steps=64", f"run_dir={split}"]) == 0
    assert main([f"resume={split}", "total_steps=96"]) == 0

    def rows(run):
        return [{k: v for k, v in r.items() if k != "time_s"} for r in read_metrics(run / "metrics.jsonl")]

    assert [r["iteration"] for r in rows(split)] == [1, 2, 3]
    assert rows(split) == rows(straight)
    assert (split / "params.msgpack").read_bytes() == (straight / "params.msgpack").read_bytes()
    summary = json.loads((split / "summary.json").read_text())
    assert summary["resumed_from"] == 2
    policy, where = read_policy(split, 6, 2)
    assert where["iteration"] == 3
    assert np.all(np.isfinite(policy.mean_action(jnp.zeros((1, 6)))))


@pytest.mark.slow
def test_steps_after_an_early_stop_are_skipped_and_change_nothing(monkeypatch):
    """With a KL target, once the policy steps have stopped no gradient is computed (the
    cond's zero branch), and the run equals one that computes and discards them."""
    overrides = ["ppo.target_kl=1e-6", "ppo.num_epochs=6", "explore=coherent"]
    skipped = run_iterations(overrides)
    from coherent_jax.agents.onpolicy import OnPolicyTrainer

    monkeypatch.setattr(OnPolicyTrainer, "_grad_unless_stopped", lambda self, f, p, sub, stopped: f(p, sub))
    computed = run_iterations(overrides)
    applied = float(skipped[1]["train/updates_applied"])
    assert 1 <= applied < 6 * 2  # stopped early (TINY has two minibatches per epoch)
    assert applied == float(computed[1]["train/updates_applied"])
    assert leaves_close(skipped[0].params, computed[0].params)
    for key, value in skipped[1].items():
        assert np.isfinite(value) == np.isfinite(computed[1][key]), key
        assert np.allclose(value, computed[1][key], rtol=1e-5, atol=1e-6, equal_nan=True), key


def test_help_names_only_defaults_an_algorithm_changes():
    """``[algo=sac: V]`` beside an option and the ``changes these defaults`` line list only
    values that differ from the option's default (SAC's lr equals PPO's: not a change)."""
    text = help_text()
    changes = 0
    for line in text.splitlines():
        m = re.match(r"  (\S+)=(\S+)\s.*\[algo=(\w+): ([^\]]+)\]", line)
        if m:
            changes += 1
            assert m.group(2) != m.group(4), line
    assert changes >= 5
    sac = next(ln for ln in text.splitlines() if ln.startswith("algo=sac changes these defaults:"))
    assert "num_envs=8" in sac and " lr=" not in sac
