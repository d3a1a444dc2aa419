"""coherent_jax: Deep Coherent Exploration for continuous control, in JAX, on MuJoCo (its C engine or MJX)."""

import importlib as _importlib
import os as _os

# jaxlib's CPU Cholesky and triangular solves call scipy's OpenBLAS. Its own thread
# pool competes with XLA's for the cores: a batched triangular solve of the coherent
# loss's backward pass ran 100-200x slower (400 ms instead of 2 ms) with OpenBLAS
# threads than with one. One thread per call is what XLA's parallelism expects.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


try:
    from threadpoolctl import threadpool_limits as _threadpool_limits
except ImportError:  # pragma: no cover - threadpoolctl is a dependency
    _threadpool_limits = None
if _threadpool_limits is not None:  # the same limit when numpy/scipy were imported before this package
    _threadpool_limits(limits=int(_os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")

__version__ = "0.1.0"

# The Python API (docs/api.md), imported on first use: ``import coherent_jax`` stays free of
# JAX, which only training and the policy need. ``coherent_jax.train`` is the command-line
# module (``python -m coherent_jax.train``); the function that trains is ``learn``.
_LAZY = {
    "learn": "coherent_jax.api",
    "Config": "coherent_jax.config",
    "ConfigError": "coherent_jax.config",
    "make_config": "coherent_jax.config",
    "load_policy": "coherent_jax.api",
    "TrainResult": "coherent_jax.api",
    "PolicyFunction": "coherent_jax.api",
    "Policy": "coherent_jax.policy",
    "TrainedPolicy": "coherent_jax.policy",
    "Callback": "coherent_jax.run.outputs",
    "Stop": "coherent_jax.run.outputs",
}
__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'coherent_jax' has no attribute {name!r}")
    value = getattr(_importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
