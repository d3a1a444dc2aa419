"""What a run's start-up imports: MJX without its Warp engine (coherent_jax.envs.quiet), unless
asked for; muted either way, and ``warp`` importable afterwards. In fresh processes, since the
test process imported MJX already."""

import subprocess
import sys

import pytest
from helpers import child_env

from coherent_jax.envs.quiet import WARP_VAR

PROBE = (
    "import sys; import coherent_jax.envs.brax_env; import mujoco.mjx.warp as w; "
    "print('warp' in sys.modules, w.WARP_INSTALLED, 'brax.envs.base' in sys.modules); "
    "import warp; print(warp.__name__)"
)


@pytest.mark.parametrize(("value", "loaded"), [(None, "False False True"), ("1", "True True True")])
def test_mjx_is_imported_without_its_warp_engine_unless_asked(value, loaded):
    env = {k: v for k, v in child_env().items() if k != WARP_VAR}
    if value is not None:
        env[WARP_VAR] = value
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == loaded, out.stdout  # printed first: MJX's own notes were muted
    assert lines[-1] == "warp"  # importable afterwards
    assert "Failed to import" not in out.stdout + out.stderr
