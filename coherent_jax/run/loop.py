"""The host loop that drives training: one run, or a grid of runs vmapped into one program.

`run_loop` is the only training loop; ``python -m coherent_jax.train`` runs it over
one train state and ``python -m coherent_jax.sweep`` over a stack of grid points'
states (``vmap(trainer.iteration)``). Either way it

* says "compiling ..." and then how long the compile took, apart from training time;
* runs the iterations with a progress bar (env steps; one rate: training env steps/s);
* evaluates every ``eval_every`` iterations and at the end (deterministic episodes);
* writes one row per iteration to each point's ``metrics.jsonl`` and, with
  ``tensorboard=true``, to TensorBoard event files in the point's ``tb/`` (with
  ``wandb=true`` also to the point's W&B run, `coherent_jax.run.outputs`);
* calls a single run's callbacks with each row (`coherent_jax.run.outputs`);
* writes ``checkpoint.msgpack`` (the whole state, `coherent_jax.run.checkpoint`) every
  ``checkpoint_every`` iterations, at the end, and when SIGINT/SIGTERM or a callback stops it;
* continues from a checkpoint (``resume``), recomputing the rows past it, so the
  metrics equal those of an uninterrupted run;
* guards against divergence after every iteration: a non-finite loss (of an
  iteration that applied an update) or parameter. A single run stops with
  `DivergenceError`. In a sweep the diverged point is reported by name and marked:
  its rows stop at the last good iteration, its summary names the reason and the
  aggregate leaves it out; the other points continue unchanged (vmapped points never
  exchange values, so a NaN in one cannot reach another). The sweep stops when every
  point has diverged.

Its steps are named functions of a `loop_state.Session`: `start_session` (devices,
keys, initial or restored state), `compile_programs`, `open_outputs`, then per
iteration `iterate` (which calls `guard`), `sink_metrics`, `save_checkpoint` and
`show_progress`, and `close_outputs`.

The divergence guard's checks (`check_finite`): after every iteration each live point's
loss metric of an iteration that applied an update, and every parameter, must be finite.
A single run stops with `DivergenceError`, naming the iteration, the quantity and the
last good checkpoint; a sweep marks the point and continues.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from coherent_jax.agents.trainer import Trainer
from coherent_jax.config.checks import rounding_note
from coherent_jax.envs.host_gym import host_pool
from coherent_jax.run import devices
from coherent_jax.run.checkpoint import CHECKPOINT, Checkpoint, LoopState, encode_checkpoint
from coherent_jax.run.devices import restore_state, state_to_bytes
from coherent_jax.run.loop_state import (
    CALLBACK,
    DivergenceError,
    Job,
    Outcome,
    Programs,
    Session,
    StopRequest,
    env_error,
    to_float,
)
from coherent_jax.run.outputs import call_on_iteration
from coherent_jax.run.rundir import METRICS, PREFIX, atomic_write, truncate_metrics
from coherent_jax.sweep_axis import vmap_points


def run_keys(seed: int):
    """(key, init_key) of a run: ``init_key`` starts the state, ``key`` is split once per evaluation.

    A sweep derives each grid point's keys with this same function, so a point runs the
    single run's program with its settings: equal up to float rounding (the vmapped
    batch reorders sums), which a chaotic task amplifies over training.
    """
    key = jax.random.PRNGKey(seed)
    key, init_key = jax.random.split(key)
    return key, init_key


def _per_point(values: dict[str, Any], n: int) -> dict[str, Any]:
    """Metrics as float64 arrays of one value per point ([n])."""
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
            from coherent_jax.run.tb_events import EventWriter  # lazy: tensorboardX takes 0.2 s

            # purge_step hides events a killed run wrote past the checkpoint.
            purge = start * cfg.steps_per_iteration + 1 if resumed else None
            writers.append(EventWriter(d / "tb", purge_step=purge))
        else:
            writers.append(None)
    return files, writers


def start_session(job: Job, resume: Checkpoint | None, t_start: float) -> Session:
    """Step 1, start: the devices, the keys (`run_keys`), the initial or restored state.

    Says "compiling ..." before anything slow. A resumed state takes its structure
    from tracing ``init`` and its values from the checkpoint; its loop state and
    evaluation key continue where the checkpoint left them.
    """
    cfg, trainer, n = job.cfg, job.trainer, job.num_points
    available = devices.resolve_num_devices(cfg.num_devices, cfg.env)
    keys = [run_keys(s) for s in job.seeds]
    if job.points:
        num_devices = devices.point_device_count(n, available)
        key = jnp.stack([k for k, _ in keys])
        init_key = jnp.stack([k for _, k in keys])
    else:
        num_devices = available
        devices.check_env_split(cfg.num_envs, num_devices)
        key, init_key = keys[0]
    # The engine `physics=auto` resolved to (trainers keep their training env in `.env`).
    physics = getattr(getattr(trainer, "env", None), "physics", cfg.physics)
    devices_note = f" on {num_devices} devices" if num_devices > 1 else ""
    note = rounding_note(cfg)
    if note:
        print(f"{PREFIX} {note}" + (" per point" if job.points else ""), flush=True)
    print(f"{PREFIX} {job.label} physics={physics}: compiling{devices_note} ...", flush=True)

    t_compile = time.perf_counter()
    loop = LoopState(eval_key=jax.device_get(key).tolist())
    start = 0
    if resume is None:
        if job.points:
            state, shardings = devices.init_points(trainer, init_key, job.hparams, num_devices)
        else:
            state, shardings = devices.init_state(trainer, init_key, num_devices, cfg.num_envs)
    else:
        # Several processes: each reads the checkpoint, only process 0 has a run_dir.
        checkpoint_path = Path(cfg.resume or job.run_dir or ".") / CHECKPOINT
        if job.points:
            template = jax.eval_shape(vmap_points(trainer.init), init_key, job.hparams)
            state = restore_state(template, resume.state_bytes, checkpoint_path)
            state, shardings = devices.shard_points(state, num_devices)
        else:
            template = jax.eval_shape(trainer.init, init_key)
            state = restore_state(template, resume.state_bytes, checkpoint_path)
            state, shardings = devices.shard_state(state, num_devices, cfg.num_envs)
        loop, start = resume.loop, resume.iteration
        key = jnp.asarray(loop.eval_key, dtype=jnp.uint32)
        pool = host_pool(getattr(trainer, "env", None))
        if pool is not None and resume.host is not None:  # a Gymnasium env: its copies on the host
            pool.restore(resume.host)
    return Session(
        job=job,
        num_devices=num_devices,
        physics=physics,
        state=state,
        shardings=shardings,
        key=key,
        loop=loop,
        start=start,
        resumed=resume is not None,
        t_start=t_start,
        t_compile=t_compile,
    )


def compile_programs(run: Session) -> None:
    """Step 2, compile: the iteration, the evaluation, the parameter check, the key split.

    Says how long the compile took (the state's init or restore included), apart
    from the training time that follows.
    """
    job, trainer, cfg = run.job, run.job.trainer, run.job.cfg

    def params_finite(s):
        leaves = jax.tree.leaves(trainer.export_params(s))
        return jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves if jnp.issubdtype(x.dtype, jnp.inexact)])
        )

    vmapped = vmap_points if job.points else (lambda f: f)
    run.programs = Programs(
        iteration=devices.compile_iteration(trainer, run.state, run.shardings, points=job.points),
        evaluate=jax.jit(vmapped(trainer.evaluate)).lower(run.state, run.key).compile(),
        check_params=jax.jit(vmapped(params_finite)).lower(run.state).compile(),
        split=jax.jit(vmapped(jax.random.split)),
    )
    run.compile_s = time.perf_counter() - run.t_compile
    print(
        f"{PREFIX} compiled in {run.compile_s:.1f} s; {cfg.num_iterations} iterations of "
        f"{cfg.steps_per_iteration} env steps"
        + (" per point" if job.points else "")
        + (f"; resuming after iteration {run.start}" if run.resumed else ""),
        flush=True,
    )


def open_outputs(run: Session, stop: StopRequest) -> None:
    """The per-point loop values, the metrics files, TensorBoard writers and the progress bar.

    Several processes: only process 0 has the run directory, but all take part in
    gathering a checkpoint's state, and all agree on a stop before the first iteration.
    """
    job, cfg, loop, n = run.job, run.job.cfg, run.loop, run.job.num_points
    # Per-point loop state as arrays; a single run keeps scalars in its checkpoint.
    run.last_return = np.broadcast_to(np.asarray(loop.last_return, np.float64), (n,)).copy()
    run.last_eval = {k: np.asarray(v, np.float64).reshape(n) for k, v in loop.last_eval.items()}
    run.diverged = {int(k): v for k, v in loop.diverged.items()}
    run.elapsed_before = loop.elapsed_s
    run.files, run.writers = _open_outputs(job, run.start, run.resumed)
    run.checkpoints = devices.from_writer(job.run_dir is not None)
    run.bar = tqdm(
        total=cfg.num_iterations * cfg.steps_per_iteration,
        initial=run.start * cfg.steps_per_iteration,
        unit="step",
        disable=not cfg.progress or not devices.is_writer(),  # one progress bar per run
        dynamic_ncols=True,
        mininterval=1.0,
        # One rate: the postfix's training env steps/s (tqdm's own would count compile and eval).
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}{postfix}]",
    )
    run.done = run.start
    run.saved = run.start if run.resumed else -1
    # A signal to one process stops all of them after the same iteration; the agreed
    # value, not the local one, decides (a signal may arrive after the agreement).
    run.stopping = devices.largest(stop.signum or 0)


def iterate(run: Session, i: int) -> dict[str, Any]:
    """Step 3, iterate: iteration ``i + 1``, its divergence guard, and an evaluation when due.

    Returns the iteration's metrics per point (float64 [n] arrays), the evaluation's
    merged in on an evaluation row; updates the timers and the last returns.
    """
    job, cfg, loop, n, programs = run.job, run.job.cfg, run.loop, run.job.num_points, run.programs
    t0 = time.perf_counter()
    run.state, metrics = programs.iteration(run.state)
    metrics = _per_point(devices.to_host(metrics), n)
    finite = np.asarray(devices.to_host(programs.check_params(run.state))).reshape(n)
    loop.train_s += time.perf_counter() - t0
    guard(run, i + 1, metrics, finite)
    if i == cfg.num_iterations - 1 or (cfg.eval_every > 0 and (i + 1) % cfg.eval_every == 0):
        t0 = time.perf_counter()
        keys_now = programs.split(run.key)
        run.key, eval_key = (keys_now[:, 0], keys_now[:, 1]) if job.points else (keys_now[0], keys_now[1])
        run.last_eval = _per_point(devices.to_host(programs.evaluate(run.state, eval_key)), n)
        loop.eval_s += time.perf_counter() - t0
        metrics.update(run.last_eval)
    ret = metrics["train/episode_return"]
    run.last_return = np.where(np.isnan(ret), run.last_return, ret)
    return metrics


def guard(run: Session, it: int, metrics: dict[str, Any], finite: Any) -> None:
    """Step 4, guard: `check_finite` for every point still live after iteration `it`.

    A single run raises `DivergenceError`; a sweep marks the point as diverged (its
    rows stop here), names it on stderr and continues with the others.
    """
    job = run.job
    for j in range(job.num_points):
        if j in run.diverged:
            continue
        try:
            view = PointView(job.trainer, j) if job.points else job.trainer
            one = {k: float(v[j]) for k, v in metrics.items()}
            check_finite(it, one, bool(finite[j]), run.state, view, job.run_dir, max(run.saved, 0))
        except DivergenceError as exc:
            if not job.points:
                raise
            run.diverged[j] = str(exc).split("; last good", 1)[0].split("; no checkpoint", 1)[0]
            print(
                f"{PREFIX} warning: point {job.names[j]} {run.diverged[j]}; its rows stop here, "
                "the other points continue",
                file=sys.stderr,
                flush=True,
            )


def sink_metrics(run: Session, it: int, metrics: dict[str, Any]) -> list[dict[str, Any] | None]:
    """Step 5, sink metrics: iteration `it`'s row in each live point's ``metrics.jsonl`` and W&B
    run (``wandb=true``; step: the iteration), its finite scalars in TensorBoard (step: env steps).
    Returns the rows, one per point (None for a diverged one), as the files hold them."""
    cfg = run.job.cfg
    env_steps = it * cfg.steps_per_iteration
    time_s = run.elapsed_before + time.perf_counter() - run.t_start
    rows: list[dict[str, Any] | None] = []
    for j in range(run.job.num_points):
        row = {"iteration": it, "env_steps": env_steps, "time_s": time_s}
        row.update({k: to_float(v[j]) for k, v in metrics.items()})
        rows.append(None if j in run.diverged else row)
    for j, (f, w) in enumerate(zip(run.files, run.writers, strict=True)):
        row = rows[j]
        if row is None:
            continue
        f.write(json.dumps(row) + "\n")
        f.flush()
        if run.job.trackers:
            run.job.trackers[j].log(row, it)
        if w is not None:
            w.add_scalars({k: float(v[j]) for k, v in metrics.items() if math.isfinite(v[j])}, env_steps)
    return rows


def save_checkpoint(run: Session) -> None:
    """Step 6, checkpoint: the whole state and the loop's state after ``run.done`` iterations.

    Every process gathers the state (a collective); only the one with the run
    directory writes it, atomically. The metrics rows and TensorBoard events of those
    iterations are already on disk (`sink_metrics` writes them through), so a run
    killed at any point leaves none of them behind the checkpoint.
    """
    job, loop, points = run.job, run.loop, run.job.points
    loop.eval_key = jax.device_get(run.key).tolist()
    loop.elapsed_s = run.elapsed_before + time.perf_counter() - run.t_start
    loop.last_return = run.last_return.tolist() if points else float(run.last_return[0])
    loop.last_eval = {k: v.tolist() if points else float(v[0]) for k, v in run.last_eval.items()}
    loop.diverged = {str(k): v for k, v in run.diverged.items()}
    state_bytes = state_to_bytes(run.state)  # every process: the state is gathered from all
    if not job.run_dir:
        return
    pool = host_pool(getattr(job.trainer, "env", None))  # a Gymnasium env's copies on the host
    host = None if pool is None else pool.snapshot()
    steps = run.done * job.cfg.steps_per_iteration
    blob = encode_checkpoint(job.cfg, run.done, steps, loop, state_bytes, host)
    atomic_write(job.run_dir / CHECKPOINT, blob)


def show_progress(run: Session) -> None:
    """The progress bar after ``run.done`` iterations: training env steps/s, last return, last evaluation."""
    n, steps = run.job.num_points, run.job.cfg.steps_per_iteration
    run.bar.update(steps)
    live = [j for j in range(n) if j not in run.diverged and math.isfinite(run.last_return[j])]
    run.bar.set_postfix(
        sps=f"{n * run.done * steps / max(run.loop.train_s, 1e-9):.0f}",
        ret=f"{np.mean(run.last_return[live]):.1f}" if live else "nan",
        eval=eval_text(run.last_eval),
        refresh=False,
    )


def eval_text(last_eval: dict[str, Any]) -> str:
    """The progress bar's last evaluation return (mean over points): ``-`` before the first."""
    if not last_eval:
        return "-"
    return f"{np.nanmean(last_eval['eval/episode_return']):.1f}"


def close_outputs(run: Session) -> None:
    """The progress bar, the metrics files and the TensorBoard writers, closed."""
    run.bar.close()
    for f in run.files:
        f.close()
    for w in run.writers:
        if w is not None:
            w.close()


def run_loop(
    job: Job,
    stop: StopRequest | None,
    resume: Checkpoint | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
) -> Outcome:
    """Runs `job` from scratch or from `resume`, until the budget is spent or `stop` is requested.

    The steps: `start_session`, `compile_programs`, then per iteration `iterate` (with
    `guard`), `sink_metrics`, the job's callbacks (`coherent_jax.run.outputs.call_on_iteration`;
    one that asks to stop is a `StopRequest.request`) and, every ``checkpoint_every``
    iterations, at the end and on a stop, `save_checkpoint`. ``progress_fn(iteration,
    metrics)`` receives a single run's metrics (Python floats) after every iteration. Raises
    `DivergenceError` when a single run diverges (see the module docstring for sweeps).

    Runs under `stop`, or under a stop request of its own when called from Python (`stop` None).
    Callbacks are a single run's: a sweep's `Job` with callbacks is a `ValueError`.
    """
    if job.callbacks and job.points:
        raise ValueError("invalid callbacks for a sweep (allowed: callbacks of a single run)")
    with contextlib.ExitStack() as stack:
        stop = stop or stack.enter_context(StopRequest())
        cfg, n = job.cfg, job.num_points
        run = start_session(job, resume, time.perf_counter())
        compile_programs(run)
        open_outputs(run, stop)
        try:
            for i in range(run.start, cfg.num_iterations):
                if run.stopping or stop.reason:
                    break
                try:
                    metrics = iterate(run, i)
                except Exception:
                    failed = env_error(run, i + 1)
                    if failed is None:
                        raise
                    raise failed from None
                rows = sink_metrics(run, i + 1, metrics)
                run.done = i + 1
                if progress_fn:
                    progress_fn(run.done, {k: float(v[0]) for k, v in metrics.items()})
                reason = call_on_iteration(job.callbacks, rows[0]) if job.callbacks else None
                if reason is not None:
                    stop.request(reason)
                every = cfg.checkpoint_every > 0 and run.done % cfg.checkpoint_every == 0
                run.stopping = devices.largest(stop.signum or 0)
                halt = bool(run.stopping) or stop.reason is not None
                if run.checkpoints and (i == cfg.num_iterations - 1 or every or halt):
                    save_checkpoint(run)
                    run.saved = run.done
                show_progress(run)
                if len(run.diverged) == n:
                    break
            if (run.stopping or stop.reason) and run.checkpoints and run.saved != run.done:
                save_checkpoint(run)  # stopped before the first iteration: resume starts here
        finally:
            close_outputs(run)
        return Outcome(
            state=run.state,
            loop=run.loop,
            start=run.start,
            done=run.done,
            compile_s=run.compile_s,
            num_devices=run.num_devices,
            physics=run.physics,
            stopped_by=(
                signal.Signals(run.stopping).name if run.stopping else CALLBACK if stop.reason else None
            ),
            last_return=[float(x) for x in run.last_return],
            last_eval={k: [float(x) for x in v] for k, v in run.last_eval.items()},
            diverged=run.diverged,
            wall_s=run.elapsed_before + time.perf_counter() - run.t_start,
            stop_reason=stop.reason if not run.stopping else None,
        )


class PointView:
    """One point of a stacked state, for `check_finite`'s parameter search."""

    def __init__(self, trainer: Trainer, index: int) -> None:
        self.trainer, self.index = trainer, index

    def export_params(self, states: Any) -> Any:
        return jax.tree.map(lambda x: x[self.index], self.trainer.export_params(states))


def first_non_finite(tree: Any) -> str:
    """Path of the first array of `tree` (on the host) holding a NaN or an infinity."""
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
    trainer: Trainer | PointView,
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
