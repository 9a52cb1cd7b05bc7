"""The compiled kernels built by the install (``flight_sw/_sgmc.c``, ``flight_sw/_treesc.c``), loaded with ctypes.

Each is optional at run time: a caller gets None when the extension is not there (no C compiler at
install time) and runs its numpy reference instead, with the same arithmetic.
"""

from __future__ import annotations

import ctypes
import importlib.util

# the extensions, each with what it computes and how much slower its numpy reference is (docs/benchmarks/pipeline.md:
# SGM 96 against 26 ms on a pair's slab; the trees 342 against 30 ms on a real pair's 77k points)
KERNELS = {
    "flight_sw._sgmc": "the SGM aggregation (~4x slower)",
    "flight_sw._treesc": "the P(safe) trees (~11x slower)",
}


def missing_kernels() -> list[str]:
    """What the install did not build, said as :data:`KERNELS` says it ([] when every kernel loads): the build is
    optional (``setup.py``), so a machine without a C compiler installed and ran slower without a word."""
    return [what for module, what in KERNELS.items() if load_kernel(module) is None]


def kernels_note(missing: list[str]) -> str:
    """A one-line warning naming the missing kernels ("" when none)."""
    if not missing:
        return ""
    return (
        f"the install built no compiled kernel for {' or '.join(missing)}: the numpy reference runs instead, with the "
        "same results, and deadlines and timings are of it (install gcc and the Python headers, then "
        "`.venv/bin/pip install -e .` builds them)"
    )


def load_kernel(module: str) -> ctypes.CDLL | None:
    """The shared library of the extension ``module`` (e.g. ``"flight_sw._sgmc"``), or None if it is not there."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return None
    try:
        return ctypes.CDLL(spec.origin)
    except OSError:
        return None
