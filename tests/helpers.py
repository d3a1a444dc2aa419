"""What several test modules share: the environment the tests' subprocesses start with,
and the tables of the Brax tasks that two modules check."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The smallest benchmark setting: pointmass, 4 envs x 8 steps, 16-unit networks; SAC
# with batch 16 and 8 updates per iteration.
TINY_BENCH = ("env=pointmass", "num_envs=4", "unroll_length=8", "policy_hidden=[16]", "value_hidden=[16]")
TINY_BENCH_SAC = ("sac.batch_size=16", "sac.utd_ratio=0.25")

# The test run's compilation cache (made by conftest.pytest_configure), and the compile
# time from which a program is worth caching.
CACHE_VAR = "COHERENT_JAX_TEST_COMPILE_CACHE"
CACHE_MIN_COMPILE_S = 0.5


def child_env() -> dict[str, str]:
    """The environment of a test's subprocess: this one's, the project on PYTHONPATH, and
    the test run's compilation cache, so that a resumed run, a repeated command or a sweep
    after its single-run twin loads its programs instead of compiling them again.

    Loading a cached program logs a C++ warning per program ("Assume version
    compatibility", pjrt_executable.cc) on stderr, which the command-line tests read;
    TF_CPP_MIN_LOG_LEVEL=2 keeps C++ warnings off stderr (errors still show)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    if os.environ.get(CACHE_VAR):
        env["JAX_COMPILATION_CACHE_DIR"] = os.environ[CACHE_VAR]
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(CACHE_MIN_COMPILE_S)
        env["TF_CPP_MIN_LOG_LEVEL"] = "2"
    return env


# Brax's re-creations (MJX, or Brax's generalized pipeline) and the pure-JAX test task:
# (observation size, action size).
BRAX_SIZES = {
    "brax-halfcheetah": (17, 6),
    "brax-hopper": (11, 3),
    "brax-walker2d": (17, 6),
    "brax-ant": (27, 8),
    "brax-humanoid": (244, 17),
    "brax-inverted_pendulum": (4, 1),
    "brax-inverted_double_pendulum": (8, 1),
    "brax-reacher": (11, 2),
    "brax-swimmer": (8, 2),
    "pointmass": (6, 2),
    # Gymnasium's classic tasks in pure JAX, with Brax's interface (test_classic_tasks.py).
    "mountain_car_continuous": (2, 1),
    "pendulum": (3, 1),
}
# The Brax tasks whose MJX programs test_native_physics.py compiles to hold native
# MuJoCo to MJX step by step; it also makes the registry smoke test's checks of them
# (test_envs.py), so that each MJX program is compiled once in the suite.
MJX_SIDE_BY_SIDE = ("brax-inverted_pendulum", "brax-halfcheetah")


def native_and_mjx_rollouts(task: str, n: int, steps: int):
    """Obs after reset, then (obs, reward, done) of `steps` steps, for MJX and native from the same keys.

    MJX's program is compiled without XLA's backend optimisation, as in the smoke test of
    `test_envs.py`: a few steps run in no time either way, and the compile is most of the
    test's time."""
    import jax

    from coherent_jax.envs import make_brax_env
    from coherent_jax.envs.physics import NativePhysics

    native, brax_env = NativePhysics(task), make_brax_env(task)
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, n, native.action_size), minval=-1, maxval=1)

    def run(reset, step, options=None):
        def go(keys, actions):
            state = reset(keys)

            def body(s, a):
                s = step(s, a)
                return s, (s.obs, s.reward, s.done)

            return state.obs, jax.lax.scan(body, state, actions)[1]

        return jax.jit(go).lower(keys, actions).compile(options)(keys, actions)

    mjx = run(jax.vmap(brax_env.reset), jax.vmap(brax_env.step), {"xla_backend_optimization_level": 0})
    nat = run(native.reset, native.step)
    return mjx, nat


def load_experiment(name: str):
    """experiments/NAME.py as a module, registered in sys.modules (its dataclasses need it,
    and report.py imports reproduce by name)."""
    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location(name, root / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def commit_all(repo: Path, message: str = "start") -> list[str]:
    """Makes `repo` a git repository with every file in it committed; returns the git
    command prefix (with a throwaway identity) for the test's further commands."""
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    for args in (["init", "-q"], ["add", "-A"], ["commit", "-q", "-m", message]):
        subprocess.run(git + args, check=True, capture_output=True)
    return git


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli, reflected polynomial 0x82F63B78), bit by bit: a reference
    for the event files' checksums that shares no code with tensorboardX's table."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC: ((c >> 15 | c << 17) + 0xa282ead8) mod 2^32."""
    c = crc32c(data)
    return (((c >> 15) | (c << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def read_events(path: Path) -> list:
    """The Events of one TensorBoard event file, every record whole and both its CRCs right."""
    import struct

    from tensorboardX.proto import event_pb2

    data, pos, events = path.read_bytes(), 0, []
    while pos < len(data):
        assert pos + 12 <= len(data), f"{path}: a truncated record header at byte {pos}"
        header = data[pos : pos + 8]
        (length,) = struct.unpack("<Q", header)
        (header_crc,) = struct.unpack("<I", data[pos + 8 : pos + 12])
        assert header_crc == masked_crc32c(header), f"{path}: bad length CRC at byte {pos}"
        end = pos + 12 + length
        assert end + 4 <= len(data), f"{path}: a truncated record at byte {pos}"
        body = data[pos + 12 : end]
        assert struct.unpack("<I", data[end : end + 4])[0] == masked_crc32c(body), f"{path}: bad CRC"
        events.append(event_pb2.Event.FromString(body))
        pos = end + 4
    return events


def tensorboard_scalars(tb_dir: Path) -> dict[str, dict[int, float]]:
    """tag -> {step: value} from every event file in `tb_dir`, in file-name order (later
    files overwrite a step), each read by `read_events`."""
    scalars: dict[str, dict[int, float]] = {}
    for path in sorted(tb_dir.glob("events.out.tfevents.*")):
        for event in read_events(path):
            for value in event.summary.value:
                scalars.setdefault(value.tag, {})[event.step] = value.simple_value
    return scalars
