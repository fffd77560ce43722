"""The seed allocator: no two streams (or blocks of one) share a seed, every
seed fits Mitsuba's 32 bits, and a stream refuses to hand out more than it holds."""

import pytest

from mcillum.validation.plan import seeds


def all_streams(seed_set: int = 0) -> list[seeds.Stream]:
    """Every block of every stream of seed set ``seed_set``."""
    return [seeds.stream(name, b, seed_set) for name, layout in seeds.STREAMS.items()
            for b in range(layout.blocks)]


def test_no_two_streams_overlap():
    streams = sorted(all_streams(), key=lambda s: s.first)
    for a, b in zip(streams, streams[1:]):
        assert a.last < b.first, f"{a.name} [{a.first}, {a.last}] overlaps {b.name} " \
                                 f"[{b.first}, {b.last}]"
    assert streams[0].first >= 0 and streams[-1].last < 2 ** 32


def test_overlap_check_finds_an_overlap(monkeypatch):
    """The check above fails on a layout whose streams do overlap."""
    monkeypatch.setitem(seeds.STREAMS, "bench", seeds.Layout(899_999, 10))
    streams = sorted(all_streams(), key=lambda s: s.first)
    assert any(a.last >= b.first for a, b in zip(streams, streams[1:]))


def test_streams_keep_the_seeds_validation_has_always_used():
    """Renders of a validation stay bit-identical across the refactoring that
    introduced the allocator: same seeds for the same stages."""
    assert seeds.stream("ladder", 3).take(2) == [30_000, 30_001]
    assert seeds.stream("speed", 1).seed(0) == 510_000
    assert seeds.stream("failure").seed(5) == 700_005
    assert seeds.stream("replication").seed(0) == 800_000
    assert seeds.stream("sunless").seed(0) == 750_000
    assert seeds.stream("sunless_replication").seed(0) == 850_000
    assert seeds.stream("compile").seed() == 999_999
    assert seeds.stream("reference").seed(7) == 1_000_007


def test_a_stream_refuses_what_it_does_not_hold():
    with pytest.raises(ValueError, match="holds 1 seeds"):
        seeds.stream("compile").seed(1)
    with pytest.raises(ValueError, match="holds 10000 seeds"):
        seeds.stream("ladder", 0).take(10_001)
    with pytest.raises(ValueError, match="block 50 is outside"):
        seeds.stream("ladder", 50)
    with pytest.raises(KeyError, match="no seed stream 'nope'"):
        seeds.stream("nope")


def test_seed_sets_are_disjoint_repeats():
    """Seed set S shifts every seed by S·0x9E3779B9 mod 2³²: within a set the
    streams still never overlap; across sets the seeds differ; set 0 is the
    table of the module doc."""
    base = {s.name: s.take(min(s.size, 2000)) for s in all_streams()}
    shifted = {s.name: s.take(min(s.size, 2000)) for s in all_streams(1)}
    assert seeds.stream("ladder", 2, 1).seed(3) == (20_003 + seeds.SET_STEP) % 2 ** 32
    every = [x for xs in shifted.values() for x in xs]
    assert len(every) == len(set(every))
    assert all(0 <= x < 2 ** 32 for x in every)
    assert not set(every) & {x for xs in base.values() for x in xs}
    for outside in (-1, 1000):
        with pytest.raises(ValueError, match="0…999"):
            seeds.stream("ladder", 2, outside)
    assert seeds.stream("ladder", 2).seed(3) == 20_003
