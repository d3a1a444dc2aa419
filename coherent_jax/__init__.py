"""coherent_jax: Deep Coherent Exploration for continuous control, in JAX on MJX."""

import os as _os

# jaxlib's CPU Cholesky and triangular solves call scipy's OpenBLAS. Its own thread
# pool competes with XLA's for the cores: a batched triangular solve of the coherent
# loss's backward pass ran 100-200x slower (400 ms instead of 2 ms) with OpenBLAS
# threads than with one. One thread per call is what XLA's parallelism expects.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _limit_loaded_blas() -> None:
    """Applies the same limit when numpy/scipy were imported before this package."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        return
    threadpool_limits(limits=int(_os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")


_limit_loaded_blas()

__version__ = "0.1.0"
