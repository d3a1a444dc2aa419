"""What a run gives out as it goes, beside its run directory's record: the user's callbacks,
the Weights & Biases mirror, and the format of evaluation videos. No JAX.

**Callbacks**: user code the training loop calls, to watch a run, log it elsewhere or stop it.

    class StopAt(coherent_jax.Callback):
        def on_evaluation(self, row):
            self.best = row["eval/episode_return"]

        def on_iteration(self, row):
            return row.get("eval/episode_return", -inf) >= 100.0   # True: stop here

    coherent_jax.learn(cfg, callbacks=[StopAt()])

A callback is any object with an ``on_iteration`` method (`CallbackLike`); ``on_start``,
``on_evaluation`` and ``on_end`` are called where it has them. `Callback` is a base class with
all four, every one a no-op by default:

* ``on_start(info)``: once, before the first iteration, with a `StartInfo` (the config, the run
  directory, the iteration the run starts after: 0, or a resumed checkpoint's);
* ``on_evaluation(row)``: on the rows that hold an evaluation (``eval/*`` keys), before
  ``on_iteration`` of the same row;
* ``on_iteration(row) -> bool | Stop | None``: after every iteration, with its row exactly as
  ``metrics.jsonl`` holds it (``iteration``, ``env_steps``, ``time_s``, ``train/*``, ``eval/*``
  on evaluation rows; None where a value was not finite). A true value or a `Stop` stops training
  after this iteration, as SIGINT/SIGTERM do: a checkpoint is written, the summary's
  ``stopped_by`` is ``"callback"`` and its ``stop_reason`` says why, and ``resume=`` continues
  from there as if the run had not stopped;
* ``on_end(summary)``: once, with the summary (also when a signal or a callback stopped the
  run; not when it raised, e.g. on a divergence).

Every callback sees every row, in the order given, even after an earlier one asked to stop.
The ``call_on_*`` functions are what the loop calls; they run in the host loop, between compiled
iterations, so a callback cannot change what the iteration computes: a run with callbacks
that do not stop it is bit-identical to one without.

**Weights & Biases**: ``wandb=true`` (the optional extra ``pip install -e ".[wandb]"``).

A run with ``wandb=true`` logs to one W&B run per training run (per grid point in a
sweep, grouped by the sweep's directory name):

* the resolved config (`config.to_dict`, exactly what ``config.yaml`` records), once;
* every metrics row the run writes to ``metrics.jsonl``, at ``step`` = the iteration;
* evaluation videos (``python -m coherent_jax.evaluate RUN_DIR video=true`` on such a
  run attaches its video to the same W&B run);
* the final summary (``summary.json``) as the W&B run's summary.

It never needs the network: unless ``WANDB_MODE`` is set in the environment, the mode
is ``offline`` and everything stays in ``RUN_DIR/wandb/`` (``wandb sync RUN_DIR/wandb/offline-run-*``
uploads it later). W&B's own cache, data and artifact directories (and, offline, its
config directory) are pointed there too (`wandb_environment`), unless the user set them,
so nothing is written under the home directory. ``WANDB_MODE=online`` (after ``wandb login``)
logs live: `wandb_preflight` refuses it without credentials before the run directory exists, and
a server that does not answer within ``wandb_init_timeout`` seconds ends the run in one line.

The W&B run id is drawn once and kept in ``RUN_DIR/wandb-run.json``; ``resume=RUN_DIR``
and ``evaluate`` reopen the same id with ``resume="allow"``, so a resumed run continues
the same W&B run. A resumed run recomputes the iterations after its checkpoint
bit-identically, so rows logged again for those steps carry the values already logged.

**Videos** (`coherent_jax.run.evaluation` renders and writes them): MP4 with ``ffmpeg`` on
the PATH, else GIF (`video_suffix`, `check_video_path`).

TensorBoard's event files are `coherent_jax.run.tb_events`'s, which the loop imports only
with ``tensorboard=true``.
"""

from __future__ import annotations

import configparser
import contextlib
import json
import netrc
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, Protocol, runtime_checkable
from urllib.parse import urlparse

from coherent_jax.config import Config, ConfigError, cli

WANDB_PROJECT = "coherent_jax"
WANDB_RUN_FILE = "wandb-run.json"
WANDB_INSTALL_HINT = 'wandb=true needs Weights & Biases: pip install -e ".[wandb]"'
WANDB_MODES = ("offline", "online", "disabled", "shared", "dryrun", "run")  # what W&B accepts
WANDB_ONLINE_MODES = ("online", "shared", "run")  # those that reach the server
WANDB_SERVER = "https://api.wandb.ai"
WANDB_INIT_TIMEOUT = 30.0  # seconds; the config's ``wandb_init_timeout``
VIDEO_FORMATS = (".mp4", ".gif")
VIDEO_PATH_ALLOWED = "a writable .gif path, or .mp4 when ffmpeg is on the PATH"


# --- callbacks ------------------------------------------------------------------------------------


class StartInfo(NamedTuple):
    """What ``on_start`` receives: the run's config, its directory (None: no directory, a run
    called with none) and the iteration it starts after (0 for a new run)."""

    config: Config
    run_dir: Path | None
    start_iteration: int


class Stop(NamedTuple):
    """What ``on_iteration`` returns to stop training, with the reason the summary records."""

    reason: str = "a callback asked to stop"


class Callback:
    """The base of a user's callback: override the hooks you need (see the module's docstring)."""

    def on_start(self, info: StartInfo) -> None:
        """Once, before the first iteration."""

    def on_iteration(self, row: dict[str, Any]) -> bool | Stop | None:
        """After every iteration; True or a `Stop` stops training after it."""
        return None

    def on_evaluation(self, row: dict[str, Any]) -> None:
        """On each row that holds an evaluation (``eval/*``)."""

    def on_end(self, summary: dict[str, Any]) -> None:
        """Once, with the run's summary."""


@runtime_checkable
class CallbackLike(Protocol):
    """What the loop calls: any object with ``on_iteration``; ``on_start``, ``on_evaluation`` and
    ``on_end`` are optional (called where the object has them). `Callback` is one."""

    def on_iteration(self, row: dict[str, Any]) -> bool | Stop | None: ...


HOOKS = ("on_start", "on_iteration", "on_evaluation", "on_end")
_ALLOWED = "allowed: objects with an on_iteration method, e.g. coherent_jax.Callback subclasses"


def _problem(cb: Any) -> str | None:
    """Why `cb` is not a callback (one line), or None."""
    if isinstance(cb, type):
        return f"the class {cb.__name__}, not an instance of it ({cb.__name__}())"
    if not isinstance(cb, CallbackLike):
        return f"a {type(cb).__name__} without an on_iteration method"
    not_callable = [h for h in HOOKS if hasattr(cb, h) and not callable(getattr(cb, h))]
    return f"a {type(cb).__name__} whose {', '.join(not_callable)} is not a method" if not_callable else None


def checked_callbacks(callbacks: Iterable[Any] | None) -> tuple[CallbackLike, ...]:
    """`callbacks` as a tuple; anything but a list of objects with ``on_iteration`` (and hooks that
    are methods) is a `ConfigError` naming the object and what it lacks."""
    if callbacks is None:
        return ()
    if isinstance(callbacks, (CallbackLike, str)) or not isinstance(callbacks, Iterable):
        raise ConfigError(f"invalid callbacks {callbacks!r} (allowed: a list of callbacks; {_ALLOWED})")
    found = tuple(callbacks)
    for cb in found:
        problem = _problem(cb)
        if problem:
            raise ConfigError(f"invalid callback {cb!r}: {problem} ({_ALLOWED})")
    return found


def call_on_start(callbacks: Sequence[CallbackLike], info: StartInfo) -> None:
    """``on_start`` of each callback that has it."""
    for cb in callbacks:
        hook = getattr(cb, "on_start", None)  # optional
        if hook is not None:
            hook(info)


def call_on_iteration(callbacks: Sequence[CallbackLike], row: dict[str, Any]) -> str | None:
    """``on_evaluation`` (on an evaluation row, where a callback has it) and ``on_iteration`` of
    each callback; the reason to stop of the first that asked to (None: go on)."""
    evaluated = any(k.startswith("eval/") for k in row)
    reasons = []
    for cb in callbacks:
        on_evaluation = getattr(cb, "on_evaluation", None)  # optional
        if evaluated and on_evaluation is not None:
            on_evaluation(dict(row))
        answer = cb.on_iteration(dict(row))  # each its own copy: one callback cannot change another's row
        if isinstance(answer, Stop):
            reasons.append(answer.reason)
        elif answer is not None and bool(answer):
            reasons.append(f"{type(cb).__name__}.on_iteration returned {answer!r}")
    return reasons[0] if reasons else None


def call_on_end(callbacks: Sequence[CallbackLike], summary: dict[str, Any]) -> None:
    """``on_end`` of each callback that has it."""
    for cb in callbacks:
        hook = getattr(cb, "on_end", None)  # optional
        if hook is not None:
            hook(summary)


class TrackingError(RuntimeError):
    """W&B was asked for and cannot be used (one line: what and how to fix it)."""


def wandb_available() -> bool:
    """Whether the optional ``wandb`` package is importable."""
    try:
        import wandb  # noqa: F401  # lazy: optional dependency
    except ImportError:
        return False
    return True


def _wandb() -> Any:
    """The optional ``wandb`` module (`require_wandb` says how to install it when it is missing)."""
    import wandb  # lazy: optional dependency

    return wandb


def require_wandb() -> None:
    """Raises `TrackingError` with the install command when ``wandb`` is missing."""
    if not wandb_available():
        raise TrackingError(WANDB_INSTALL_HINT)


def wandb_mode() -> str:
    """``WANDB_MODE`` when the user set it, else ``offline``: a run never needs the network."""
    return os.environ.get("WANDB_MODE") or "offline"


def check_wandb_mode(value: str) -> str:
    """`value` if W&B accepts it as a mode; else raises `TrackingError` naming the allowed ones."""
    if value not in WANDB_MODES:
        raise TrackingError(f"invalid value for WANDB_MODE: {value!r} (allowed: {', '.join(WANDB_MODES)})")
    return value


def wandb_credentials(environ: Mapping[str, str]) -> str | None:
    """Where W&B would find credentials for its server, without asking it; None when nowhere.

    Looked up as ``wandb`` does: ``WANDB_API_KEY`` or ``WANDB_IDENTITY_TOKEN_FILE``, a
    ``.netrc`` entry for the server's host (``NETRC``, else ``~/.netrc``), the ``api_key``
    of W&B's settings file (``WANDB_CONFIG_DIR/settings``, else ``~/.config/wandb/settings``).
    `environ` stands for the environment (``HOME`` included), so the lookup can be tested.
    """
    for name in ("WANDB_API_KEY", "WANDB_IDENTITY_TOKEN_FILE"):
        if environ.get(name):
            return name
    home = Path(environ.get("HOME") or Path.home())
    host = urlparse(environ.get("WANDB_BASE_URL") or WANDB_SERVER).hostname or ""
    netrc_files = [Path(environ["NETRC"])] if environ.get("NETRC") else [home / ".netrc", home / "_netrc"]
    for path in netrc_files:
        with contextlib.suppress(OSError, netrc.NetrcParseError):
            if path.is_file() and netrc.netrc(str(path)).authenticators(host):
                return str(path)
    config_dir = (
        Path(environ["WANDB_CONFIG_DIR"]) if environ.get("WANDB_CONFIG_DIR") else home / ".config/wandb"
    )
    settings = configparser.ConfigParser()
    with contextlib.suppress(OSError, configparser.Error):
        settings.read(config_dir / "settings")
        if settings.get("default", "api_key", fallback=""):
            return str(config_dir / "settings")
    return None


def wandb_preflight(environ: Mapping[str, str] | None = None) -> None:
    """What ``wandb=true`` needs, checked before anything is written: the package, a valid
    ``WANDB_MODE`` and, to log online, credentials. Raises `TrackingError` in one line."""
    environ = os.environ if environ is None else environ
    require_wandb()
    wanted = check_wandb_mode(environ.get("WANDB_MODE") or "offline")
    if wanted in WANDB_ONLINE_MODES and wandb_credentials(environ) is None:
        raise TrackingError(
            f"WANDB_MODE={wanted} needs W&B credentials and none were found (allowed: run `wandb login` "
            "or set WANDB_API_KEY; or leave WANDB_MODE unset to log offline into RUN_DIR/wandb/)"
        )


def wandb_environment(root: Path, environ: Mapping[str, str]) -> dict[str, str]:
    """The W&B variables a run sets (those the user has not): its mode, silence, its cache, data and
    artifact directories under ``root/wandb/``; its config directory too unless it logs online
    (online, the user's login and server settings live there)."""
    wanted = environ.get("WANDB_MODE") or "offline"
    dirs = {"WANDB_CACHE_DIR": "cache", "WANDB_DATA_DIR": "data", "WANDB_ARTIFACT_DIR": "artifacts"}
    if wanted not in WANDB_ONLINE_MODES:
        dirs["WANDB_CONFIG_DIR"] = "config"
    values = {
        "WANDB_MODE": wanted,
        "WANDB_SILENT": "true",  # W&B's own notices ("Loaded credentials ...") off the run's stderr
        **{k: str(Path(root) / "wandb" / v) for k, v in dirs.items()},
    }
    return {k: v for k, v in values.items() if not environ.get(k)}


@contextlib.contextmanager
def wandb_session(root: Path) -> Iterator[None]:
    """W&B's process-wide state for the runs of one directory `root`: the variables of
    `wandb_environment` set while inside, and W&B's service (started with them) torn down
    on leaving, so the next session starts its own. A W&B run the calling program had
    already started (``wandb.run``, from Python) keeps its service: no teardown then."""
    wandb = _wandb()
    had_run = wandb.run is not None
    added = wandb_environment(root, os.environ)
    os.environ.update(added)
    try:
        yield
    finally:
        try:
            if not had_run:
                wandb.teardown()
        finally:
            for key in added:
                os.environ.pop(key, None)


def _identity(run_dir: Path, name: str, group: str | None) -> dict[str, Any]:
    """The W&B run's id, name and group, drawn once and then read from ``WANDB_RUN_FILE``."""
    path = run_dir / WANDB_RUN_FILE
    if path.exists():
        return json.loads(path.read_text())
    identity = {"id": secrets.token_hex(4), "project": WANDB_PROJECT, "name": name, "group": group}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(identity, indent=1) + "\n")
    tmp.replace(path)
    return identity


class WandbRun:
    """One W&B run mirroring one training run (or one grid point of a sweep)."""

    def __init__(self, run: Any) -> None:
        self._run = run

    @classmethod
    def open(
        cls,
        run_dir: Path,
        config: Mapping[str, Any] | None,
        name: str,
        group: str | None = None,
        init_timeout: float = WANDB_INIT_TIMEOUT,
    ) -> WandbRun:
        """Starts (or, with an id in ``run_dir/RUN_FILE``, resumes) the W&B run of ``run_dir``.

        ``config`` is logged as the run's config (None: leave it as logged before,
        for a process such as `evaluate` that only adds media). W&B gets `init_timeout`
        seconds to start; any failure to start (no answer from the server, credentials
        it refuses) raises `TrackingError` in one line.
        """
        require_wandb()
        wandb = _wandb()
        identity = _identity(run_dir, name, group)
        settings = wandb.Settings(
            silent=True, console="off", x_disable_stats=True, init_timeout=float(init_timeout)
        )
        try:
            run = wandb.init(
                project=identity["project"],
                id=identity["id"],
                name=identity["name"],
                group=identity["group"],
                dir=str(run_dir),
                mode=check_wandb_mode(wandb_mode()),
                resume="allow",
                config=dict(config) if config is not None else None,
                settings=settings,
                reinit="create_new",
            )
        except TrackingError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever stops W&B from starting means the same here
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise TrackingError(
                f"W&B could not start the run of {str(run_dir)!r} (WANDB_MODE={wandb_mode()}, "
                f"wandb_init_timeout={init_timeout:g} s): {reason} "
                "(allowed: a reachable W&B server, or WANDB_MODE unset to log offline)"
            ) from None
        return cls(run)

    def log(self, row: Mapping[str, float | None], step: int) -> None:
        """One metrics row at ``step`` (the iteration); None values (no evaluation) are left out."""
        self._run.log({k: v for k, v in row.items() if v is not None}, step=int(step))

    def video(self, path: Path, step: int | None, key: str = "eval/video") -> None:
        """An evaluation video (MP4 or GIF) at ``step`` (None: W&B's next step, after every row
        already logged, which a resumed W&B run requires of a late addition)."""
        wandb = _wandb()
        fmt = "gif" if Path(path).suffix == ".gif" else "mp4"
        self._run.log({key: wandb.Video(str(path), format=fmt)}, step=None if step is None else int(step))

    def finish(self, summary: Mapping[str, Any] | None = None) -> None:
        """Writes ``summary`` (the run's ``summary.json``) as the W&B summary and closes the run."""
        if summary:
            for key, value in summary.items():
                self._run.summary[key] = value
        self._run.finish()


class Mirrors:
    """The W&B runs of a run's points (empty without ``wandb=true``) and their final summaries.

    ``runs[j]`` mirrors point j (a single run: one); the loop logs each point's rows to it
    (`coherent_jax.run.loop.sink_metrics`). The caller sets ``summaries`` once it has written
    them; `mirrored` then finishes each run with its own.
    """

    def __init__(self, runs: list[WandbRun]) -> None:
        self.runs = runs
        self.summaries: Sequence[Mapping[str, Any]] | None = None


@contextlib.contextmanager
def mirrored(
    points: Sequence[tuple[Path, Mapping[str, Any], str]],
    group: str | None = None,
    init_timeout: float = WANDB_INIT_TIMEOUT,
) -> Iterator[Mirrors]:
    """Opens one `WandbRun` per (directory, config, name) of `points`, and finishes them all on exit.

    Finished with their summaries when the caller set them (the run completed), else
    without (stopped, diverged: a resume continues the same W&B runs); a run that fails
    to open finishes those opened before it. W&B's files go under the points' common
    directory (`wandb_session`). Nothing is opened for no points, so a run without
    ``wandb=true`` never imports ``wandb``.
    """
    mirrors = Mirrors([])
    if not points:
        yield mirrors
        return
    root = Path(os.path.commonpath([str(Path(d).absolute()) for d, _, _ in points]))
    with wandb_session(root):
        try:
            for d, config, name in points:
                mirrors.runs.append(WandbRun.open(d, config, name, group, init_timeout))
            yield mirrors
        finally:
            for j, run in enumerate(mirrors.runs):
                run.finish(mirrors.summaries[j] if mirrors.summaries else None)


# --- videos ---------------------------------------------------------------------------------------


def video_suffix() -> str:
    """``.mp4`` where ``ffmpeg`` is on the PATH, else ``.gif`` (Pillow writes those)."""
    return ".mp4" if shutil.which("ffmpeg") else ".gif"


def check_video_path(text: str) -> str:
    """A ``video_path`` that can be written: ``.gif``, or ``.mp4`` with ``ffmpeg``; raises `ValueError`."""
    suffix = Path(text).suffix.lower()
    if suffix not in VIDEO_FORMATS or (suffix == ".mp4" and not shutil.which("ffmpeg")):
        raise ValueError(text)
    return cli.output_file(text)
