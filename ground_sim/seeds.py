"""The two scene-seed sets: tune on one, report the other.

Every study that chooses parameters (flight presets, thresholds, the k of a
test against uncertainty) may look only at :data:`TUNING_SEEDS`. Every figure
that is quoted as a result (RESULTS.md, closing notes, the landing Monte
Carlo) comes from :data:`HELD_OUT_SEEDS`, which nothing is tuned on. A scene
seed selects the terrain of a named scene (``ground_sim/presets``); the
renderer's noise seeds derive from it.
"""

from __future__ import annotations

TUNING_SEEDS: tuple[int, ...] = tuple(range(10))
HELD_OUT_SEEDS: tuple[int, ...] = tuple(range(1000, 1100))
SEED_SETS: dict[str, tuple[int, ...]] = {"tuning": TUNING_SEEDS, "held-out": HELD_OUT_SEEDS}


def seed_set_of(seed: int) -> str:
    """``"tuning"``, ``"held-out"`` or ``"other"`` for a scene seed."""
    for name, seeds in SEED_SETS.items():
        if seed in seeds:
            return name
    return "other"


def not_held_out(seeds: list[int] | tuple[int, ...], seed_set: str) -> str:
    """Why figures over ``seeds`` (drawn as ``seed_set``) are not held-out results, or "" when they are: tuning
    seeds, or a list that pools them with held-out ones, were only named ("tuning seeds 0 (1)"), and their
    figures read as quotable (QA 65b M3)."""
    other = [x for x in seeds if seed_set_of(x) != "held-out"]
    if seed_set == "held-out" and not other:
        return ""
    what = (
        f"{seed_set} seeds"
        if len(other) == len(seeds)
        else f"seed(s) {','.join(map(str, other[:5]))} (not held-out) pooled with held-out ones"
    )
    return f"{what}: these figures are not held-out results (quote --seed-set held-out, the default)"


def seed_runs(seeds: list[int] | tuple[int, ...]) -> str:
    """``1000-1005,1010,1012-1099``: sorted, each run of consecutive seeds as a range (a note listed 99 seeds one by
    one; QA of stop 74)."""
    runs: list[list[int]] = []
    for s in sorted(set(seeds)):
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def describe_seeds(seeds: list[int] | tuple[int, ...], seed_set: str) -> str:
    """``held-out seeds 1000-1005 (6)``: runs of consecutive seeds as ranges (:func:`seed_runs`)."""
    return f"{seed_set} seeds {seed_runs(seeds)} ({len(seeds)})"
