"""The host loop that drives training: one run, or a grid of runs vmapped into one program.

`run_loop` is the only training loop; ``python -m coherent_jax.train`` runs it over
one train state and ``python -m coherent_jax.sweep`` over a stack of grid points'
states (``vmap(trainer.iteration)``). Either way it

* says "compiling ..." and then how long the compile took, apart from training time;
* runs the iterations with a progress bar (env steps; one rate: training env steps/s);
* evaluates every ``eval_every`` iterations and at the end (deterministic episodes);
* writes one row per iteration to each point's ``metrics.jsonl`` and, with
  ``tensorboard=true``, to TensorBoard event files in the point's ``tb/``;
* writes ``checkpoint.msgpack`` (the whole state, `coherent_jax.runs`) every
  ``checkpoint_every`` iterations, at the end, and when SIGINT/SIGTERM stops it;
* continues from a checkpoint (``resume``), recomputing the rows past it, so the
  metrics equal those of an uninterrupted run;
* guards against divergence after every iteration: a non-finite loss (of an
  iteration that applied an update) or parameter. A single run stops with
  `DivergenceError`. In a sweep the diverged point is reported by name and marked:
  its rows stop at the last good iteration, its summary names the reason and the
  aggregate leaves it out; the other points continue unchanged (vmapped points never
  exchange values, so a NaN in one cannot reach another). The sweep stops when every
  point has diverged.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coherent_jax.config import Config
from coherent_jax.runs import (
    CHECKPOINT,
    METRICS,
    PREFIX,
    Checkpoint,
    LoopState,
    atomic_write,
    encode_checkpoint,
    restore_state,
    state_to_bytes,
    truncate_metrics,
)
from coherent_jax.sweep_axis import vmap_points


class DivergenceError(RuntimeError):
    """A loss or a parameter became non-finite; the message names the iteration and the quantity."""


def quiet_imports() -> None:
    """Imports MJX once with its stdout muted: it prints lines when its optional `warp` backend is missing."""
    with contextlib.redirect_stdout(io.StringIO()):
        import mujoco.mjx  # noqa: F401


def run_keys(seed: int):
    """(key, init_key) of a run: ``init_key`` starts the state, ``key`` is split once per evaluation.

    A sweep derives each grid point's keys with this same function, so a point equals
    the single run with its settings.
    """
    import jax

    key = jax.random.PRNGKey(seed)
    key, init_key = jax.random.split(key)
    return key, init_key


def to_float(x: Any) -> float | None:
    """A metric as JSON has it: a float, or None when not finite."""
    value = float(x)
    return value if math.isfinite(value) else None


class StopRequest:
    """Turns SIGINT/SIGTERM into a request to stop after the current iteration.

    Installed before anything slow (imports, compiles), so a Ctrl-C at any moment
    ends the program cleanly instead of with a traceback. A second signal ends the
    process at once, by the signal's default action.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)
            return
        self.signum = signum
        print(
            f"\n{PREFIX} {signal.Signals(signum).name}: stopping after the current step",
            file=sys.stderr,
            flush=True,
        )

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signum).name if self.signum is not None else None

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def first_non_finite(tree: Any) -> str:
    """Path of the first array of `tree` (on the host) holding a NaN or an infinity."""
    import jax
    import numpy as np

    for where, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(tree))[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.inexact) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(where)
    return "?"


def check_finite(
    it: int,
    metrics: dict[str, float],
    params_ok: bool,
    state: Any,
    trainer: Any,
    run_dir: Path | None,
    saved: int,
) -> None:
    """Raises `DivergenceError` if a loss metric or a parameter is non-finite.

    Losses are checked only when the iteration applied an update
    (``train/updates_applied`` > 0, or absent): SAC reports NaN losses by design while
    its replay buffer warms up. Parameters are always checked. `saved` is the
    iteration of the last checkpoint written (the one a resume starts from).
    """
    updated = metrics.get("train/updates_applied", 1.0) > 0
    bad = [k for k, v in metrics.items() if updated and "loss" in k and not math.isfinite(v)]
    if not bad and params_ok:
        return
    if bad:
        quantity = f"{bad[0]} = {metrics[bad[0]]}"
    else:
        quantity = f"parameter {first_non_finite(trainer.export_params(state))} is not finite"
    kept = (
        f"; last good checkpoint: iteration {saved} in {run_dir / CHECKPOINT}"
        if run_dir and (run_dir / CHECKPOINT).exists()
        else "; no checkpoint was written before it"
    )
    raise DivergenceError(f"diverged at iteration {it}: {quantity}{kept}")


@dataclasses.dataclass(frozen=True)
class Job:
    """What the loop runs.

    Attributes:
      cfg: the settings every point shares (shapes, schedule, outputs).
      trainer: `coherent_jax.agents.make_trainer`'s object for `cfg`.
      seeds: one seed per point (a single run: one).
      names: one name per point, for messages.
      run_dir: where the checkpoint lives (None: nothing is written).
      point_dirs: per point, where its metrics, TensorBoard files, parameters and
        summary go (a single run: ``[run_dir]``).
      hparams: a sweep's stacked hyperparameters (leading axis: points); None for a
        single run, whose state is not vmapped.
      label: how the start-up line names the job.
    """

    cfg: Config
    trainer: Any
    seeds: list[int]
    names: list[str]
    run_dir: Path | None
    point_dirs: list[Path] | None
    hparams: Any = None
    label: str = ""

    @property
    def points(self) -> bool:
        return self.hparams is not None

    @property
    def num_points(self) -> int:
        return len(self.seeds)


@dataclasses.dataclass
class Outcome:
    """How the loop ended.

    Attributes:
      state: the final train state (stacked for a sweep).
      loop: the loop's state (timers; per-point last returns and evaluations).
      start, done: the iteration it started after and the last one done.
      compile_s: seconds of compilation in this process.
      num_devices: devices the work was spread over.
      physics: the physics engine the trainer's env resolved to.
      stopped_by: the signal's name when SIGINT/SIGTERM ended it early, else None.
      last_return, last_eval: per point (lists of length num_points).
      diverged: per diverged point (index), the reason.
      wall_s: seconds since the run began, over all its sessions.
    """

    state: Any
    loop: LoopState
    start: int
    done: int
    compile_s: float
    num_devices: int
    physics: str
    stopped_by: str | None
    last_return: list[float]
    last_eval: dict[str, list[float]]
    diverged: dict[int, str]
    wall_s: float


class _PointView:
    """One point of a stacked state, for `check_finite`'s parameter search."""

    def __init__(self, trainer: Any, index: int) -> None:
        self.trainer, self.index = trainer, index

    def export_params(self, states: Any) -> Any:
        import jax

        return jax.tree.map(lambda x: x[self.index], self.trainer.export_params(states))


def _per_point(values: dict[str, Any], n: int) -> dict[str, Any]:
    """Metrics as float64 arrays of one value per point ([n])."""
    import numpy as np

    return {k: np.asarray(v, np.float64).reshape(n) for k, v in values.items()}


def _open_outputs(job: Job, start: int, resumed: bool):
    """Per point: the metrics file (rows past `start` dropped on resume) and a TensorBoard writer or None."""
    cfg = job.cfg
    files, writers = [], []
    for d in job.point_dirs or []:
        if resumed:
            truncate_metrics(d / METRICS, start)
        files.append(open(d / METRICS, "a" if resumed else "w"))
        if cfg.tensorboard:
            from tensorboardX import SummaryWriter

            # purge_step hides events a killed run wrote past the checkpoint.
            purge = start * cfg.steps_per_iteration + 1 if resumed else None
            writers.append(SummaryWriter(str(d / "tb"), purge_step=purge, flush_secs=30))
        else:
            writers.append(None)
    return files, writers


def run_loop(
    job: Job,
    stop: StopRequest,
    resume: Checkpoint | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
) -> Outcome:
    """Runs `job` from scratch or from `resume`, until the budget is spent or `stop` is requested.

    ``progress_fn(iteration, metrics)`` receives a single run's metrics (Python
    floats) after every iteration. Raises `DivergenceError` when a single run
    diverges (see the module docstring for sweeps).
    """
    import jax
    import jax.numpy as jnp
    import numpy as np
    from tqdm.auto import tqdm

    from coherent_jax import multihost, sharding

    cfg, trainer, n = job.cfg, job.trainer, job.num_points
    t_start = time.perf_counter()
    available = sharding.resolve_num_devices(cfg.num_devices)
    keys = [run_keys(s) for s in job.seeds]
    if job.points:
        num_devices = sharding.point_device_count(n, available)
        key = jnp.stack([k for k, _ in keys])
        init_key = jnp.stack([k for _, k in keys])
    else:
        num_devices = available
        sharding.check_env_split(cfg.num_envs, num_devices)
        key, init_key = keys[0]
    # The engine `physics=auto` resolved to (trainers keep their training env in `.env`).
    physics = getattr(getattr(trainer, "env", None), "physics", cfg.physics)
    devices_note = f" on {num_devices} devices" if num_devices > 1 else ""
    print(f"{PREFIX} {job.label} physics={physics}: compiling{devices_note} ...", flush=True)

    t0 = time.perf_counter()
    loop = LoopState(eval_key=jax.device_get(key).tolist())
    start = 0
    if resume is None:
        if job.points:
            state, shardings = sharding.init_points(trainer, init_key, job.hparams, num_devices)
        else:
            state, shardings = sharding.init_state(trainer, init_key, num_devices, cfg.num_envs)
    else:  # the state's structure from tracing init, its values from the checkpoint
        # Several processes: each reads the checkpoint, only process 0 has a run_dir.
        checkpoint_path = Path(cfg.resume or job.run_dir or ".") / CHECKPOINT
        if job.points:
            template = jax.eval_shape(vmap_points(trainer.init), init_key, job.hparams)
            state = restore_state(template, resume.state_bytes, checkpoint_path)
            state, shardings = sharding.shard_points(state, num_devices)
        else:
            template = jax.eval_shape(trainer.init, init_key)
            state = restore_state(template, resume.state_bytes, checkpoint_path)
            state, shardings = sharding.shard_state(state, num_devices, cfg.num_envs)
        loop, start = resume.loop, resume.iteration
        key = jnp.asarray(loop.eval_key, dtype=jnp.uint32)

    def params_finite(s):
        leaves = jax.tree.leaves(trainer.export_params(s))
        return jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves if jnp.issubdtype(x.dtype, jnp.inexact)])
        )

    vmapped = vmap_points if job.points else (lambda f: f)
    iteration = sharding.compile_iteration(trainer, state, shardings, points=job.points)
    evaluate = jax.jit(vmapped(trainer.evaluate)).lower(state, key).compile()
    check_params = jax.jit(vmapped(params_finite)).lower(state).compile()
    split = jax.jit(vmapped(jax.random.split))
    compile_s = time.perf_counter() - t0
    print(
        f"{PREFIX} compiled in {compile_s:.1f} s; {cfg.num_iterations} iterations of "
        f"{cfg.steps_per_iteration} env steps"
        + (" per point" if job.points else "")
        + (f"; resuming after iteration {start}" if resume is not None else ""),
        flush=True,
    )

    # Per-point loop state as arrays; a single run keeps scalars in its checkpoint.
    last_return = np.broadcast_to(np.asarray(loop.last_return, np.float64), (n,)).copy()
    last_eval = {k: np.asarray(v, np.float64).reshape(n) for k, v in loop.last_eval.items()}
    diverged = {int(k): v for k, v in loop.diverged.items()}
    elapsed_before = loop.elapsed_s

    def save_checkpoint(done: int) -> None:
        loop.eval_key = jax.device_get(key).tolist()
        loop.elapsed_s = elapsed_before + time.perf_counter() - t_start
        loop.last_return = last_return.tolist() if job.points else float(last_return[0])
        loop.last_eval = {k: v.tolist() if job.points else float(v[0]) for k, v in last_eval.items()}
        loop.diverged = {str(k): v for k, v in diverged.items()}
        state_bytes = state_to_bytes(state)  # every process: the state is gathered from all
        if not job.run_dir:
            return
        blob = encode_checkpoint(cfg, done, done * cfg.steps_per_iteration, loop, state_bytes)
        atomic_write(job.run_dir / CHECKPOINT, blob)
        for w in writers:
            if w is not None:
                w.flush()

    files, writers = _open_outputs(job, start, resume is not None)
    # Several processes: only process 0 has the run directory, but all gather the state.
    checkpoints = multihost.from_writer(job.run_dir is not None)
    bar = tqdm(
        total=cfg.num_iterations * cfg.steps_per_iteration,
        initial=start * cfg.steps_per_iteration,
        unit="step",
        disable=not cfg.progress or not multihost.is_writer(),  # one progress bar per run
        dynamic_ncols=True,
        mininterval=1.0,
        # One rate: the postfix's training env steps/s (tqdm's own would count compile and eval).
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}{postfix}]",
    )
    done = start
    saved = start if resume is not None else -1
    # A signal to one process stops all of them after the same iteration; the agreed
    # value, not the local one, decides (a signal may arrive after the agreement).
    stopping = multihost.largest(stop.signum or 0)
    try:
        for i in range(start, cfg.num_iterations):
            if stopping:
                break
            t0 = time.perf_counter()
            state, metrics = iteration(state)
            metrics = _per_point(multihost.to_host(metrics), n)
            finite = np.asarray(multihost.to_host(check_params(state))).reshape(n)
            loop.train_s += time.perf_counter() - t0
            for j in range(n):
                if j in diverged:
                    continue
                try:
                    view = _PointView(trainer, j) if job.points else trainer
                    one = {k: float(v[j]) for k, v in metrics.items()}
                    check_finite(i + 1, one, bool(finite[j]), state, view, job.run_dir, max(saved, 0))
                except DivergenceError as exc:
                    if not job.points:
                        raise
                    diverged[j] = str(exc).split("; last good", 1)[0].split("; no checkpoint", 1)[0]
                    print(
                        f"{PREFIX} warning: point {job.names[j]} {diverged[j]}; its rows stop here, "
                        "the other points continue",
                        file=sys.stderr,
                        flush=True,
                    )
            last = i == cfg.num_iterations - 1
            if last or (cfg.eval_every > 0 and (i + 1) % cfg.eval_every == 0):
                t0 = time.perf_counter()
                keys_now = split(key)
                key, eval_key = (keys_now[:, 0], keys_now[:, 1]) if job.points else (keys_now[0], keys_now[1])
                last_eval = _per_point(multihost.to_host(evaluate(state, eval_key)), n)
                loop.eval_s += time.perf_counter() - t0
                metrics.update(last_eval)
            ret = metrics["train/episode_return"]
            last_return = np.where(np.isnan(ret), last_return, ret)
            env_steps = (i + 1) * cfg.steps_per_iteration
            time_s = elapsed_before + time.perf_counter() - t_start
            for j, (f, w) in enumerate(zip(files, writers, strict=True)):
                if j in diverged:
                    continue
                row = {"iteration": i + 1, "env_steps": env_steps, "time_s": time_s}
                row.update({k: to_float(v[j]) for k, v in metrics.items()})
                f.write(json.dumps(row) + "\n")
                f.flush()
                if w is not None:
                    for k, v in metrics.items():
                        if math.isfinite(v[j]):
                            w.add_scalar(k, float(v[j]), env_steps)
            done = i + 1
            if progress_fn:
                progress_fn(done, {k: float(v[0]) for k, v in metrics.items()})
            every = cfg.checkpoint_every > 0 and done % cfg.checkpoint_every == 0
            stopping = multihost.largest(stop.signum or 0)
            if checkpoints and (last or every or stopping):
                save_checkpoint(done)
                saved = done
            bar.update(cfg.steps_per_iteration)
            live = [j for j in range(n) if j not in diverged and math.isfinite(last_return[j])]
            bar.set_postfix(
                sps=f"{n * env_steps / max(loop.train_s, 1e-9):.0f}",
                ret=f"{np.mean(last_return[live]):.1f}" if live else "nan",
                eval=f"{np.nanmean(last_eval['eval/episode_return']):.1f}" if last_eval else "nan",
                refresh=False,
            )
            if len(diverged) == n:
                break
        if stopping and checkpoints and saved != done:
            save_checkpoint(done)  # stopped before the first iteration: resume starts here
    finally:
        bar.close()
        for f in files:
            f.close()
        for w in writers:
            if w is not None:
                w.close()
    return Outcome(
        state=state,
        loop=loop,
        start=start,
        done=done,
        compile_s=compile_s,
        num_devices=num_devices,
        physics=physics,
        stopped_by=signal.Signals(stopping).name if stopping else None,
        last_return=[float(x) for x in last_return],
        last_eval={k: [float(x) for x in v] for k, v in last_eval.items()},
        diverged=diverged,
        wall_s=elapsed_before + time.perf_counter() - t_start,
    )


def write_params(trainer: Any, state: Any, point_dirs: list[Path], points: bool) -> None:
    """Each point's final parameters and observation statistics (flax msgpack) in its directory.

    Several processes: every process must call it (the parameters are gathered from
    all); only process 0 has directories to write to.
    """
    import jax
    from flax import serialization

    from coherent_jax.multihost import to_host

    params = to_host(trainer.export_params(state))
    for j, d in enumerate(point_dirs):
        one = jax.tree.map(lambda x, j=j: x[j], params) if points else params
        atomic_write(d / "params.msgpack", serialization.to_bytes(one))
