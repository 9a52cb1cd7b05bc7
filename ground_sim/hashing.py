"""Deterministic counter-based random numbers: a pure function of integer keys.

Lazily generated features (craters, boulders, noise lattices) must be the same
whatever window is evaluated, so randomness is a hash of (seed, stream, cell,
index) rather than a stateful generator. splitmix64 finaliser on uint64 arrays.
"""

from __future__ import annotations

import numpy as np

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


def _mix(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def hash_u64(*keys: np.ndarray | int) -> np.ndarray:
    """Hash integer keys (broadcast together) to uint64; order matters."""
    arrs = np.broadcast_arrays(*[np.asarray(k, dtype=np.int64) for k in keys])
    h = np.full(arrs[0].shape, 0x243F6A8885A308D3, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for a in arrs:
            h = _mix(h + _GOLD + a.astype(np.uint64))
    return h


def uniform(*keys: np.ndarray | int) -> np.ndarray:
    """Uniform float64 in [0, 1) from the top 53 bits of :func:`hash_u64`."""
    return (hash_u64(*keys) >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def poisson(lam: float, u: np.ndarray, cap: int = 64) -> np.ndarray:
    """Poisson(lam) counts by inverse CDF of uniforms ``u`` (capped at ``cap``)."""
    k = np.arange(cap + 1)
    logp = -lam + k * np.log(max(lam, 1e-300)) - np.cumsum(np.log(np.maximum(k, 1)))
    cdf = np.cumsum(np.exp(logp))
    return np.searchsorted(cdf, u, side="right").clip(0, cap)
