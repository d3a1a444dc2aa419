"""Users' environments: what ``env=MODULE:NAME`` or ``env=path/to/file.py:NAME`` names,
imported (the module or the file, once per process) and taken by kind, one branch per kind
(`resolve_user_attribute`): an MJCF task (below), a Gymnasium env (checked by
`coherent_jax.envs.gym_source`, as is ``env=gym:ID``; stepped by `coherent_jax.envs.host_gym`)
or a JAX env with Brax's interface (`coherent_jax.envs.jax_env`). `load_user_task` gives the
task's registry entry and what the engines run.

An MJCF task is a `MjcfTask`: an MJCF file, the `Kinematics` fields its formulas read,
and its observation, reward and termination as pure JAX functions of those fields,
the contract of the built-in tasks (`coherent_jax.envs.mujoco_task.NativeTask`). ``NAME`` is an
attribute of the importable module ``MODULE`` (or of the Python file at that path) that
is a `MjcfTask`, a subclass of it, or a function of no arguments annotated to return
one (`task_maker`): what the attribute is is checked before it is called, so no other
callable is ever run. It runs on native MuJoCo and on MJX like Gymnasium's tasks.

`load_user_task` imports it once per process and checks it before anything runs: the
module (or file) and attribute exist, the attribute is a task or declared to make one,
the fields are `Kinematics` fields, the MJCF compiles and has actuators, and at a state
drawn from the reset distribution and after one step with zero action, traced by JAX
as training traces them, the observation is a finite vector, the reward a finite scalar
and the termination a boolean scalar. A problem raises `TaskDefinitionError` in one
line naming the task and the problem.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.util
import inspect
import os
import sys
import typing
from collections.abc import Callable
from types import ModuleType
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from coherent_jax.envs import jax_env
from coherent_jax.envs.gym_source import GYM_RULE, GymSource, gym_maker, registered_gym_env, user_gym_env
from coherent_jax.envs.mujoco_task import (
    POST_CONSTRAINT_FIELDS,
    Kinematics,
    NativeModel,
    NativeTask,
    control,
    uniform_reset,
)
from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.spec import (
    USER_TASK_FORM,
    TaskSpec,
    first_line,
    import_module,
    is_gym_id,
    is_user_task,
    refuse,
    user_task_parts,
)

# Fields every task reads (the reset and `Kinematics` need them).
ALWAYS_READ = ("qpos", "qvel")


@dataclasses.dataclass(frozen=True)
class MjcfTask:
    """A task defined by its MJCF file and its formulas in JAX.

    Attributes:
      mjcf: path of the MJCF file (relative paths from the working directory; a module
        usually builds it from its own ``__file__``).
      fields: the `Kinematics` fields the formulas read besides ``qpos`` and ``qvel``
        (``xpos``, ``site_xpos``, ``sensordata``, ...); the others are None.
      observe: `Kinematics` -> [obs_size] observation, finite.
      reward: (kin before, kin after, ctrl [nu], dt) -> scalar reward of the step; ``ctrl``
        is the control applied, ``dt`` the env step in seconds.
      terminate: `Kinematics` after a step -> boolean scalar, True where the episode ends
        in a terminal state (no bootstrap); None: never (only the time limit ends episodes).
      frame_skip: ``mj_step`` calls per env step.
      episode_length: the time limit in env steps (``episode_length=0`` of the config).
      reset_noise: (key, init_q [nq], nv) -> (qpos [nq], qvel [nv]), the initial-state
        distribution around the model's ``qpos0``; default q0 + U(-0.1, 0.1), qd U(-0.1, 0.1).
      scale_action: map the agent's action in [-1, 1] onto the actuators' ctrlrange
        (which every actuator must then declare); False passes it through.
    """

    mjcf: str | os.PathLike
    fields: tuple[str, ...]
    observe: Callable[[Kinematics], jax.Array]
    reward: Callable[[Kinematics, Kinematics, jax.Array, float], jax.Array]
    terminate: Callable[[Kinematics], jax.Array] | None = None
    frame_skip: int = 1
    episode_length: int = 1000
    reset_noise: Callable[..., tuple[jax.Array, jax.Array]] = uniform_reset(0.1, 0.1, False)
    scale_action: bool = True


class LoadedTask(NamedTuple):
    """A checked user task: its registry entry, and the `NativeTask` the engines run (an MJCF
    task) or the `GymSource` the host steps (a Gymnasium env)."""

    spec: TaskSpec
    native: NativeTask | None
    gym: GymSource | None = None


# What ``NAME`` may be, said in every refusal of another kind of attribute.
TASK_RULE = (
    "an MjcfTask, a subclass of it, or a function of no arguments annotated '-> MjcfTask'; "
    "nothing else is called (docs/tasks.md)"
)


def import_file(name: str, path: str) -> ModuleType:
    """The Python file at `path` (from the working directory), imported once per process as a
    module of its own (named after its absolute path, so two files of one name do not clash)."""
    full = os.path.abspath(path)
    if not os.path.isfile(full):
        refuse(name, f"file {path!r} not found (from {os.getcwd()})")
    module_name = "coherent_jax_task_" + hashlib.sha1(full.encode()).hexdigest()[:16]
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, full)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses of the file look their module up there
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        del sys.modules[module_name]
        refuse(name, f"cannot import file {path!r} ({first_line(exc)})")
    return module


def user_attribute(name: str) -> object:
    """The attribute ``NAME`` of ``MODULE:NAME`` or ``path/to/file.py:NAME``, imported (not called)."""
    source, attr, is_file = user_task_parts(name)
    module = import_file(name, source) if is_file else import_module(name, source)
    if not hasattr(module, attr):
        refuse(name, f"{'file' if is_file else 'module'} {source!r} has no attribute {attr!r}")
    return getattr(module, attr)


def resolve_user_attribute(name: str) -> tuple[str, Any]:
    """What ``env=name`` names, by kind, one branch per kind: (``"gymnasium"``, `GymSource`) for
    ``gym:[MODULE:]ID`` or a ``gymnasium.Env`` maker; (``"mjcf"``, `MjcfTask`) for a task or a
    maker of one (`task_maker`); (``"jax-env"``, the attribute) for a JAX env with Brax's
    interface (`coherent_jax.envs.jax_env.is_brax_env`). Only what is declared to make one of
    these is ever called."""
    if is_gym_id(name):
        return "gymnasium", registered_gym_env(name)
    obj = user_attribute(name)
    attr = user_task_parts(name)[1]
    if isinstance(obj, MjcfTask):
        return "mjcf", obj
    if jax_env.is_brax_env(obj):  # a JAX env with Brax's interface (coherent_jax.envs.jax_env)
        return "jax-env", obj
    if task_maker(obj) is None:
        return "mjcf", _made_task(name, attr, obj)
    if gym_maker(obj) is None:
        return "gymnasium", user_gym_env(name, obj)
    _fail(name, f"{attr} is {task_maker(obj)}, not {TASK_RULE}, or {GYM_RULE}")


def _made_task(name: str, attr: str, maker: Callable[[], Any]) -> MjcfTask:
    try:
        task = maker()
    except Exception as exc:
        _fail(name, f"{attr}() raised {first_line(exc)}")
    if not isinstance(task, MjcfTask):
        _fail(name, f"{attr}() returned a {type(task).__name__}, not an MjcfTask")
    return task


def task_maker(obj: Any) -> str | None:
    """None if `obj` may be called to make a task: a subclass of `MjcfTask`, or a Python function
    whose parameters all have defaults and whose return annotation resolves to `MjcfTask` (or a
    subclass). Otherwise what it is, for the refusal. Nothing is called here, so a callable that
    is not declared to make a task (``os:system``) is never run."""
    if inspect.isclass(obj):
        return None if issubclass(obj, MjcfTask) else f"the class {obj.__name__}"
    if not inspect.isfunction(obj):
        return f"of type {type(obj).__name__}"
    required = [
        p.name
        for p in inspect.signature(obj).parameters.values()
        if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    if required:
        return f"a function of arguments ({', '.join(required)})"
    try:
        returns = typing.get_type_hints(obj).get("return")
    except Exception:  # an annotation that does not resolve (a name imported only for type checkers)
        returns = None
    if not (inspect.isclass(returns) and issubclass(returns, MjcfTask)):
        return "a function without the return annotation '-> MjcfTask'"
    return None


_fail = refuse


@functools.cache
def load_model(path: str, frame_skip: int) -> NativeModel:
    """The compiled MJCF at `path`; init_q is the model's ``qpos0``. Raises `ValueError` for a
    file MuJoCo cannot compile."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)  # no MUJOCO_LOG.TXT in the working directory
    try:
        with quiet_stdio(force=True):
            model = mujoco.MjModel.from_xml_path(path)
    finally:
        mujoco.set_mju_user_warning(previous)
    init_q = np.asarray(model.qpos0, np.float32)
    return NativeModel(model, int(frame_skip), float(model.opt.timestep * frame_skip), init_q)


def _checked_settings(name: str, task: MjcfTask) -> tuple[str, ...]:
    """The fields read (``qpos``, ``qvel`` first); refuses unknown fields and bad sizes."""
    fields = (task.fields,) if isinstance(task.fields, str) else tuple(task.fields)
    unknown = [f for f in fields if f not in Kinematics._fields]
    if unknown:
        _fail(name, f"fields {unknown} are not Kinematics fields (allowed: {', '.join(Kinematics._fields)})")
    for key in ("frame_skip", "episode_length"):
        value = getattr(task, key)
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value < 2**31:
            _fail(name, f"{key}={value!r} (allowed: an integer >= 1)")
    return ALWAYS_READ + tuple(dict.fromkeys(f for f in fields if f not in ALWAYS_READ))


def _checked_model(name: str, task: MjcfTask) -> NativeModel:
    path = os.fspath(task.mjcf)
    if not os.path.isfile(path):
        _fail(name, f"MJCF file {path!r} not found")
    try:
        loaded = load_model(os.path.abspath(path), task.frame_skip)
    except ValueError as exc:
        lines = (line.strip() for line in str(exc).splitlines())
        _fail(name, f"MJCF file {path!r} does not compile ({'; '.join(line for line in lines if line)})")
    model = loaded.model
    if model.nu < 1:
        _fail(name, f"MJCF file {path!r} has no actuators (the agent acts through them)")
    if task.scale_action and not np.all(model.actuator_ctrllimited):
        _fail(name, "scale_action=True needs a ctrlrange on every actuator of the MJCF")
    return loaded


def _fields_of(data: Any, fields: tuple[str, ...]) -> Kinematics:
    return Kinematics(**{f: jnp.asarray(np.asarray(getattr(data, f)), jnp.float32)[None] for f in fields})


def _sample_states(name: str, native: NativeTask, loaded: NativeModel):
    """`Kinematics` [1, ...] at a state of the reset distribution and after one step with zero
    action (control applied, as the engines apply it), and that control."""
    model = loaded.model
    init_q, keys = jnp.asarray(loaded.init_q), jax.random.PRNGKey(0)[None]
    drawn = _run(name, "reset_noise", lambda key: native.reset_noise(key, init_q, model.nv), keys, pair=True)
    shapes = tuple(np.shape(x) for x in drawn) if isinstance(drawn, tuple) else np.shape(drawn)
    if shapes != ((model.nq,), (model.nv,)):
        _fail(
            name,
            f"reset_noise returns shapes {shapes}; expected (qpos, qvel): (({model.nq},), ({model.nv},))",
        )
    qpos, qvel = drawn
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = np.asarray(qpos), np.asarray(qvel)
    mujoco.mj_forward(model, data)
    before = _fields_of(data, native.fields)
    ctrl = control(native, jnp.zeros((model.nu,)), model.actuator_ctrlrange)
    data.ctrl[:] = np.asarray(ctrl)
    mujoco.mj_step(model, data, nstep=loaded.n_frames)
    if any(f in POST_CONSTRAINT_FIELDS for f in native.fields):
        mujoco.mj_rnePostConstraint(model, data)
    return before, _fields_of(data, native.fields), ctrl[None]


def _run(name: str, what: str, fn: Callable, *args, pair: bool = False) -> Any:
    """``fn`` vmapped over one env and jitted, as the engines run it; its per-env output, a
    NumPy array (with `pair`: a tuple of them)."""
    try:
        out = jax.jit(jax.vmap(fn))(*args)
    except Exception as exc:
        _fail(name, f"{what} fails under jax.jit/vmap ({first_line(exc)})")
    if pair and isinstance(out, tuple) and all(isinstance(x, jax.Array) for x in out):
        return tuple(np.asarray(x)[0] for x in out)
    if not isinstance(out, jax.Array):
        _fail(name, f"{what} returns a {type(out).__name__}; expected a JAX array")
    return np.asarray(out)[0]


def _check_formulas(name: str, task: MjcfTask, native: NativeTask, loaded: NativeModel) -> None:
    """Observation, reward and termination at a reset state and after one zero-action step."""
    before, after, ctrl = _sample_states(name, native, loaded)
    for when, kin in (("after a reset", before), ("after a step", after)):
        obs = _run(name, "observe", task.observe, kin)
        if obs.ndim != 1 or obs.size < 1:
            _fail(name, f"observe returns shape {obs.shape} per env; expected a vector [obs_size]")
        if not np.issubdtype(obs.dtype, np.floating):
            _fail(name, f"observe returns {obs.dtype} values; expected floats")
        if not np.all(np.isfinite(obs)):
            bad = int(np.sum(~np.isfinite(obs)))
            _fail(name, f"observe returns {bad} non-finite values of {obs.size} {when}")
    dt = loaded.dt
    reward = _run(name, "reward", lambda k0, k1, c: task.reward(k0, k1, c, dt), before, after, ctrl)
    if reward.shape != ():
        _fail(name, f"reward returns shape {reward.shape} per env; expected a scalar per env (shape ())")
    if not np.issubdtype(reward.dtype, np.number) or not np.isfinite(reward):
        _fail(name, f"reward is {reward} after a step; expected a finite number")
    if task.terminate is not None:
        done = _run(name, "terminate", task.terminate, after)
        boolean_like = done.shape == () and (
            done.dtype == np.bool_ or (np.issubdtype(done.dtype, np.number) and done in (0, 1))
        )
        if not boolean_like:
            got = f"shape {done.shape}" if done.shape else f"the value {done.tolist()!r}"
            _fail(name, f"terminate returns {done.dtype} of {got} per env; expected a boolean scalar per env")


def _native_task(task: MjcfTask, fields: tuple[str, ...], path: str) -> NativeTask:
    terminate = task.terminate

    def reward_done(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
        done = jnp.zeros(()) if terminate is None else jnp.asarray(terminate(k1))
        return task.reward(k0, k1, ctrl, dt), done

    return NativeTask(
        load=functools.partial(load_model, path, task.frame_skip),
        fields=fields,
        reset_noise=task.reset_noise,
        observe=task.observe,
        reward_done=reward_done,
        scale_action=bool(task.scale_action),
        source=f"MJCF {task.mjcf}",
    )


@functools.cache
def load_user_task(name: str) -> LoadedTask:
    """Task ``MODULE:NAME``, imported and checked (see the module's docstring); once per process.
    Raises `TaskDefinitionError` naming the task and the problem."""
    if not is_user_task(name):
        _fail(name, f"not of the form {USER_TASK_FORM}")
    kind, task = resolve_user_attribute(name)
    if kind == "jax-env":  # no NativeTask: VecEnv steps it as it steps Brax's envs
        return LoadedTask(jax_env.load_jax_env(name, task).spec, None)
    if kind == "gymnasium":
        spec = TaskSpec(
            "",
            None,
            episode_length=task.episode_length,
            description=f"a Gymnasium env of your own ({name}), stepped on the host",
            backend="gym",
            max_episode_length=task.own_limit,
        )
        return LoadedTask(spec, None, task)
    fields = _checked_settings(name, task)
    loaded = _checked_model(name, task)
    native = _native_task(task, fields, os.path.abspath(os.fspath(task.mjcf)))
    _check_formulas(name, task, native, loaded)
    spec = TaskSpec(
        "",
        None,
        episode_length=task.episode_length,
        description=f"a task of your own from {os.fspath(task.mjcf)}",
        backend="native",
        native=True,
    )
    return LoadedTask(spec, native)
