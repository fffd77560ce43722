"""Which sampler seed each render of a validation uses, decided in one place.

Renders that a statistic treats as independent must not share seeds (two
renders with one seed are the same image). Every stage therefore takes its
seeds from a named stream of :data:`STREAMS`, and no two streams overlap
(tests/test_seeds.py checks it). Streams that are split into blocks (one block
per ladder rung) hand out one block per index.

The numbers of the validation streams are those mcillum used before the
allocator existed, so a validation run renders the same images (`mcillum
bench`, which used 0, 1, …, has its own stream now):

    ladder           rung r, render i  →  10 000·r + i       (50 rungs × 10 000)
    speed            budget j, render i  →  500 000 + 10 000·j + i  (the speed stage's
                     equal-time renders at the display resolution; 9 budgets)
    speed_timing     590 000 + i         (its timed renders for the cost model)
    quadrature       block b, render i  →  600 000 + 1 000·b + i  (stages/quadrature.py: the
                     point-set estimators at N = 16, default, 256 and cosine at N·spp;
                     2n + 2 blocks for n point sets, so 80 blocks of 1 000)
    failure          700 000 + i         (K seeds per failure case)
    sunless          750 000 + i         (the same case on its map without the sun)
    replication      800 000 + i         (reserved: fresh renders that repeated a
                     rejection before the sequential tests took that over; 20 000)
    widened          820 000 + i         (the same case with its sun widened)
    widened_sequential  look j, render i  →  830 000 + 1 000·j + i
    sunless_replication 850 000 + i      (reserved, likewise)
    sequential       look j, render i  →  860 000 + 1 000·j + i  (the batches a sequential
                     test adds where the evidence is thin, stages/sequential.py; 20 looks)
    sunless_sequential  look j, render i  →  880 000 + 1 000·j + i
    bench            900 000 + i         (`mcillum bench`)
    compile          999 999             (each integrator's first, untimed render)
    reference        1 000 000 + pass    (Mitsuba's `path`, one seed per pass)

Within one scene run or failure case every stream is used once; different
scenes reuse them (they are different experiments).

Seed sets (``mcillum validate --seed-set S``; the run carries its set,
``stages.context.Run.seed_set``, and passes it to :func:`stream`): set 0 is the
table above; set S adds S·0x9E3779B9 to every seed, modulo 2³². Adding a
constant modulo 2³² maps distinct seeds to distinct seeds, so the streams of
one set still never overlap, and Mitsuba's sampler hashes its seed, so each
set is an independent repeat of the whole validation (its references
included: run/references.py puts the set into their cache key). Sets are for
calibrating the tests: how often a correct estimator fails over repeats.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Stream:
    """Seeds ``first, first + 1, …, first + size − 1``."""

    name: str
    first: int
    size: int
    shift: int = 0                  # of the seed set (module doc), added modulo 2³²

    def seed(self, i: int = 0) -> int:
        """The ``i``-th seed of the stream."""
        if not 0 <= i < self.size:
            raise ValueError(f"seed stream '{self.name}' holds {self.size} seeds; "
                             f"index {i} is outside it")
        return (self.first + i + self.shift) % SEEDS

    def take(self, k: int) -> list[int]:
        """The first ``k`` seeds."""
        if not 0 <= k <= self.size:
            raise ValueError(f"seed stream '{self.name}' holds {self.size} seeds; "
                             f"{k} were asked for")
        return [self.seed(i) for i in range(k)]

    @property
    def last(self) -> int:
        return self.first + self.size - 1


@dataclass(frozen=True)
class Layout:
    """A stream split into ``blocks`` blocks of ``size`` seeds from ``first``."""

    first: int
    size: int
    blocks: int = 1


#: Every stream: name → where its seeds lie. Seeds are 32-bit (Mitsuba's).
STREAMS = {
    "ladder": Layout(0, 10_000, blocks=50),
    "speed": Layout(500_000, 10_000, blocks=9),
    "speed_timing": Layout(590_000, 10_000),
    "quadrature": Layout(600_000, 1_000, blocks=80),
    "learning": Layout(680_000, 1_000, blocks=20),
    "failure": Layout(700_000, 50_000),
    "sunless": Layout(750_000, 50_000),
    "replication": Layout(800_000, 20_000),
    "widened": Layout(820_000, 10_000),
    "widened_sequential": Layout(830_000, 1_000, blocks=20),
    "sunless_replication": Layout(850_000, 10_000),
    "sequential": Layout(860_000, 1_000, blocks=20),
    "sunless_sequential": Layout(880_000, 1_000, blocks=20),
    "bench": Layout(900_000, 49_999),
    "budget_axis": Layout(950_000, 1_000, blocks=40),
    "compile": Layout(999_999, 1),
    "reference": Layout(1_000_000, 2 ** 32 - 1_000_000),
}


#: Mitsuba's seeds are 32-bit.
SEEDS = 2 ** 32

#: What seed set S adds to every seed (× S, modulo 2³²): the golden-ratio
#: constant, so that the sets' streams land far from each other.
SET_STEP = 0x9E3779B9

SETS = 1000


def check_set(s: int) -> int:
    """Seed set ``s`` as an int; raises ValueError outside 0…999."""
    if not 0 <= s < SETS:
        raise ValueError(f"the seed set must be in 0…{SETS - 1}, got {s}")
    return int(s)


def stream(name: str, block: int = 0, seed_set: int = 0) -> Stream:
    """Block ``block`` of the stream called ``name``, in seed set ``seed_set``
    (module doc). Raises KeyError for an unknown stream, ValueError for a
    block or seed set outside it."""
    if name not in STREAMS:
        raise KeyError(f"no seed stream '{name}'; the streams are {', '.join(STREAMS)}")
    layout = STREAMS[name]
    if not 0 <= block < layout.blocks:
        raise ValueError(f"seed stream '{name}' has {layout.blocks} block(s); "
                         f"block {block} is outside it")
    label = name if layout.blocks == 1 else f"{name}[{block}]"
    return Stream(label, layout.first + block * layout.size, layout.size,
                  check_set(seed_set) * SET_STEP % SEEDS)
