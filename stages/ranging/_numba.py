"""numba where it is installed (``numba`` is None otherwise: every compiled kernel
has a numpy twin)."""

try:
    import numba
except ImportError:  # pragma: no cover
    numba = None
