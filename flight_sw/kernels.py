"""The compiled kernels built by the install (``flight_sw/_sgmc.c``, ``flight_sw/_treesc.c``), loaded with ctypes.

Each is optional at run time: a caller gets None when the extension is not there (no C compiler at
install time) and runs its numpy reference instead, with the same arithmetic.
"""

from __future__ import annotations

import ctypes
import importlib.util


def load_kernel(module: str) -> ctypes.CDLL | None:
    """The shared library of the extension ``module`` (e.g. ``"flight_sw._sgmc"``), or None if it is not there."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return None
    try:
        return ctypes.CDLL(spec.origin)
    except OSError:
        return None
