"""The seeds only the guard draws from: plants nobody looked at.

A verdict is worth what it predicts on plants nobody tuned on, so the guard draws its
synthetic plants, and its perturbations of a real plant, from FRESH_SEEDS, a range that no
suite, test, example, tuning default or document uses (`tests/eval/test_fresh_seeds.py`
holds every file of the project to it), afresh each run from a run seed it prints and
records. `sweep` and `tune` refuse seeds of this range: nothing is chosen on them.
"""

from __future__ import annotations

import zlib

import numpy as np

from flowerpose.errors import InputError

#: The guard's seeds, written down once: a billion of them, so two runs share a plant
#: almost never.
FRESH_SEEDS = range(1_000_000_000, 2_000_000_000)


def entry_draw(run_seed: int, entry: str, plants: int) -> tuple[int, int]:
    """An entry's first plant seed (its `plants` seeds all in the range) and its
    perturbations' seed, drawn from the run seed and the entry's name."""
    rng = np.random.default_rng([run_seed, zlib.crc32(entry.encode())])
    first = int(rng.integers(FRESH_SEEDS.start, FRESH_SEEDS.stop - plants))
    return first, int(rng.integers(FRESH_SEEDS.start, FRESH_SEEDS.stop))


def refuse_fresh(seed: int, plants: int, flag: str = "--seed") -> None:
    """InputError where seeds `seed`..`seed + plants - 1` reach the guard's range: settings
    chosen on them would make its verdicts a training score."""
    if seed + plants > FRESH_SEEDS.start and seed < FRESH_SEEDS.stop:
        raise InputError(flag, f"{seed}: seeds from {FRESH_SEEDS.start:,} to "
                         f"{FRESH_SEEDS.stop - 1:,} are the guard's fresh plants, which "
                         "nothing is chosen or tuned on; use seeds below them")
