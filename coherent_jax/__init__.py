"""coherent_jax: Deep Coherent Exploration for continuous control, in JAX, on MuJoCo (its C engine or MJX)."""

import importlib as _importlib
import os as _os

from coherent_jax import compat as _compat

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
    "Policy": "coherent_jax.policy",
    "Callback": "coherent_jax.run.outputs",
    "CallbackLike": "coherent_jax.run.outputs",
    "Stop": "coherent_jax.run.outputs",
}
__all__ = ["__version__", *_LAZY]

# The names of before (docs/api.md, "Deprecated names"): each still answers, warning once
# with its successor. Attributes of the package -> the new name's dotted path:
_FORMER = {
    "TrainedPolicy": "coherent_jax.policy.Policy",
    "PolicyFunction": "coherent_jax.policy.Policy",
    "runs": "coherent_jax.run.checkpoint",
    "tracking": "coherent_jax.run.outputs",
    "divergence": "coherent_jax.run.loop",
    "presets": "coherent_jax.config.schema",
}
# Modules that moved, imported by their former names (``from coherent_jax.runs import ...``)
# -> (the module now, {a renamed attribute: its name now}):
_compat.install(
    {
        "coherent_jax.runs": ("coherent_jax.run.checkpoint", {}),
        "coherent_jax.tracking": ("coherent_jax.run.outputs", {}),
        "coherent_jax.divergence": ("coherent_jax.run.loop", {}),
        "coherent_jax.presets": ("coherent_jax.config.schema", {}),
        "coherent_jax.config.presets": ("coherent_jax.config.schema", {}),
        "coherent_jax.run.policy": (
            "coherent_jax.policy.net",
            {"Policy": "PolicyNet", "load_policy": "read_policy"},
        ),
    }
)
_former = _compat.module_getattr("coherent_jax", _FORMER, stacklevel=4)  # called by __getattr__


def __getattr__(name: str):
    if name == "train":
        # ``coherent_jax.train(config)`` was the API's function: the command-line module, which
        # still answers a call (deprecated, see its `_CallableModule`). Importing it binds it here.
        return _importlib.import_module("coherent_jax.train")
    if name not in _LAZY:
        return _former(name)  # a former name (warns once), else AttributeError
    value = getattr(_importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
