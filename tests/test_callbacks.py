"""Callbacks (coherent_jax.run.outputs) through coherent_jax.learn: the hooks see what the run
logs, a stop from a callback writes a checkpoint, and resume= from there equals a run that
was never stopped."""

import csv
import importlib.util
import json
from pathlib import Path

import pytest

import coherent_jax
from coherent_jax.config import ConfigError
from coherent_jax.run import outputs
from coherent_jax.run.checkpoint import CHECKPOINT, PARAMS
from coherent_jax.run.loop import run_loop
from coherent_jax.run.loop_state import Job
from coherent_jax.run.outputs import Callback, Stop
from coherent_jax.run.rundir import METRICS

ROOT = Path(__file__).resolve().parent.parent
TINY = {
    "env": "pointmass",
    "num_envs": 8,
    "unroll_length": 16,
    "episode_length": 40,
    "total_steps": 6 * 8 * 16,  # 6 iterations
    "eval_every": 2,
    "eval_episodes": 4,
    "checkpoint_every": 0,  # checkpoints only at the end and on a stop
    "policy_hidden": [16, 16],
    "value_hidden": [16, 16],
    "ppo": {"num_epochs": 2, "num_minibatches": 2},
    "progress": False,
    "tensorboard": False,
}
STOP_AT = 3


class Recorder(Callback):
    """Every hook's argument, in order; stops after iteration `stop_at` (None: never)."""

    def __init__(self, stop_at=None, how=True):
        self.calls, self.stop_at, self.how = [], stop_at, how

    def on_start(self, info):
        self.calls.append(("start", info))

    def on_evaluation(self, row):
        self.calls.append(("evaluation", row))

    def on_iteration(self, row):
        self.calls.append(("iteration", row))
        return self.how if row["iteration"] == self.stop_at else None

    def on_end(self, summary):
        self.calls.append(("end", summary))

    def rows(self):
        return [a for kind, a in self.calls if kind == "iteration"]


def _example(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _logged(run_dir):
    return [{k: v for k, v in json.loads(line).items() if k != "time_s"} for line in open(run_dir / METRICS)]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """An uninterrupted run with a recorder and the example's CSV logger."""
    root = tmp_path_factory.mktemp("whole")
    recorder, logger = Recorder(), _example("custom_logger").CsvLogger(root / "rows.csv")
    result = coherent_jax.learn({**TINY, "run_dir": str(root / "run")}, callbacks=[recorder, logger])
    return result, recorder, root


def test_the_hooks_see_what_the_run_logs(whole):
    result, recorder, root = whole
    kinds = [kind for kind, _ in recorder.calls]
    assert kinds[0] == "start" and kinds[-1] == "end" and kinds.count("iteration") == 6
    info = recorder.calls[0][1]
    assert info.run_dir == result.run_dir and info.start_iteration == 0 and info.config.num_envs == 8
    assert recorder.calls[-1][1] == result.summary and result.stopped_by is None
    # The rows are metrics.jsonl's, every key; evaluations on the eval rows only, before their iteration.
    assert recorder.rows() == result.metrics
    evaluated = [row["iteration"] for kind, row in recorder.calls if kind == "evaluation"]
    assert evaluated == [2, 4, 6] == [r["iteration"] for r in result.metrics if "eval/episode_return" in r]
    for i, (kind, row) in enumerate(recorder.calls):
        if kind == "evaluation":
            assert recorder.calls[i + 1] == ("iteration", row)
    # The example's CSV sink holds the same values.
    with open(root / "rows.csv") as f:
        table = list(csv.DictReader(f))
    assert [int(r["iteration"]) for r in table] == list(range(1, 7))
    for r, row in zip(table, result.metrics, strict=True):
        for key in ("train/episode_return", "eval/episode_return"):
            logged = row.get(key)  # None: no episode ended in the iteration, or no evaluation
            assert (r[key] == "") == (logged is None)
            assert logged is None or float(r[key]) == pytest.approx(logged, rel=1e-12)


def test_a_callback_stop_then_resume_equals_an_uninterrupted_run(whole, tmp_path):
    result, _, _ = whole
    run = tmp_path / "run"
    stopper = Recorder(stop_at=STOP_AT, how=Stop("enough"))
    stopped = coherent_jax.learn({**TINY, "run_dir": str(run)}, callbacks=[stopper])
    assert stopped.stopped_by == "callback" == stopped.summary["stopped_by"]
    assert stopped.summary["stop_reason"] == "enough" and stopper.calls[-1] == ("end", stopped.summary)
    assert stopped.summary["iterations"] == STOP_AT and len(stopped.metrics) == STOP_AT
    assert (run / CHECKPOINT).is_file() and not (run / PARAMS).exists()
    assert not (run / "summary.json").exists() and stopped.policy is not None

    later = Recorder()
    resumed = coherent_jax.learn({"resume": str(run)}, callbacks=[later])
    assert later.calls[0][1].start_iteration == STOP_AT and [r["iteration"] for r in later.rows()] == [
        4,
        5,
        6,
    ]
    assert resumed.stopped_by is None and resumed.summary["resumed_from"] == STOP_AT
    assert _logged(run) == _logged(result.run_dir)
    assert (run / PARAMS).read_bytes() == (result.run_dir / PARAMS).read_bytes()


def test_bad_callbacks_are_refused_before_anything_is_written(tmp_path):
    run = tmp_path / "run"
    for bad, named in [
        (print, "builtin_function_or_method"),
        (Recorder(), "a list of"),
        (object(), "object"),
    ]:
        given = bad if named == "a list of" else [bad]
        with pytest.raises(ConfigError, match=rf"^invalid callbacks? .*{named}.*coherent_jax\.Callback"):
            coherent_jax.learn({**TINY, "run_dir": str(run)}, callbacks=given)
    assert not run.exists()


class OnlyIteration:
    """A callback of the user's own, no subclass of `Callback`: ``on_iteration`` alone."""

    def __init__(self):
        self.rows = []

    def on_iteration(self, row):
        self.rows.append(row["iteration"])
        return Stop("enough") if row["iteration"] == 2 else None


class NoIteration:
    def on_end(self, summary):
        pass


class BrokenHook(OnlyIteration):
    on_end = "not a method"


def test_any_object_with_on_iteration_is_a_callback():
    """The protocol (`CallbackLike`): ``on_iteration`` required, the other hooks called where the
    object has them; a `Callback` subclass is one too."""
    duck, recorder = OnlyIteration(), Recorder()
    assert isinstance(duck, coherent_jax.CallbackLike) and isinstance(recorder, outputs.CallbackLike)
    assert outputs.checked_callbacks([duck, recorder]) == (duck, recorder)
    info = outputs.StartInfo(config=None, run_dir=None, start_iteration=0)
    outputs.call_on_start([duck, recorder], info)
    row = {"iteration": 1, "env_steps": 8, "time_s": 0.1, "eval/episode_return": -3.0}
    assert outputs.call_on_iteration([duck, recorder], row) is None
    assert outputs.call_on_iteration([duck, recorder], {**row, "iteration": 2}) == "enough"
    outputs.call_on_end([duck, recorder], {"final_eval_return": -3.0})
    assert duck.rows == [1, 2]
    assert [kind for kind, _ in recorder.calls] == ["start", *["evaluation", "iteration"] * 2, "end"]


def test_an_object_that_is_no_callback_is_refused_in_one_line_naming_what_it_lacks(tmp_path):
    run = tmp_path / "run"
    for bad, problem in [
        (NoIteration(), "a NoIteration without an on_iteration method"),
        (OnlyIteration, "the class OnlyIteration, not an instance of it (OnlyIteration())"),
        (BrokenHook(), "a BrokenHook whose on_end is not a method"),
    ]:
        with pytest.raises(ConfigError) as info:
            coherent_jax.learn({**TINY, "run_dir": str(run)}, callbacks=[bad])
        message = str(info.value)
        assert message.startswith("invalid callback ") and problem in message and "\n" not in message
    with pytest.raises(ConfigError, match=r"^invalid callbacks .*a list of callbacks"):
        outputs.checked_callbacks(OnlyIteration())  # one callback, not a list
    assert not run.exists()


def test_a_sweep_takes_no_callbacks():
    job = Job(
        cfg=None,
        trainer=None,
        seeds=[0, 1],
        names=["a", "b"],
        run_dir=None,
        point_dirs=None,
        hparams={},
        callbacks=(Callback(),),
    )
    with pytest.raises(ValueError, match="invalid callbacks for a sweep"):
        run_loop(job, None, None)


def test_every_callback_sees_every_row_and_the_first_reason_wins():
    first, second = Recorder(stop_at=1, how=Stop("first")), Recorder(stop_at=1, how=Stop("second"))
    row = {"iteration": 1, "env_steps": 8, "time_s": 0.1, "eval/episode_return": -3.0}
    assert outputs.call_on_iteration([first, second], row) == "first"
    assert [k for k, _ in first.calls] == [k for k, _ in second.calls] == ["evaluation", "iteration"]
    assert outputs.call_on_iteration([Recorder()], {**row, "iteration": 2}) is None
    assert (
        outputs.call_on_iteration([Recorder(stop_at=2)], {**row, "iteration": 2})
        == "Recorder.on_iteration returned True"
    )
    assert Callback().on_iteration(row) is None  # the base's hooks do nothing
