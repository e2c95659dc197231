"""Seeds (roadgonio/seeds.py, issue 21): the accepted range, and two different seeds never share a
random stream."""
from __future__ import annotations

import random

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.seeds import MITSUBA_SEED_MAX, SEED_MAX, cell_key, check_seed, seed_entropy


@pytest.mark.parametrize("bad", [-1, 2 ** 63, 1.0, 1.5, True, "3", None, np.float64(2.0)])
def test_a_seed_is_a_whole_number_in_range(bad):
    with pytest.raises(InputError, match="seed"):
        check_seed(bad)


def test_accepted_seeds_come_back_whole():
    assert check_seed(np.int64(7)) == 7 and check_seed(SEED_MAX) == SEED_MAX and check_seed(0) == 0
    with pytest.raises(InputError, match="32-bit"):
        check_seed(MITSUBA_SEED_MAX + 1, maximum=MITSUBA_SEED_MAX)


def decode(words: list[int]) -> tuple[int, ...]:
    """The values of an entropy list, read back (written apart from seed_entropy)."""
    *body, n = words
    values, i = [], 0
    while i < len(body):
        count = body[i]
        v = sum(w << (32 * k) for k, w in enumerate(body[i + 1:i + 1 + count]))
        values.append(v)
        i += 1 + count
    assert len(values) == n and i == len(body)
    return tuple(values)


def test_entropy_is_one_to_one_and_never_ends_in_zero():
    rnd = random.Random(7)
    for _ in range(2000):
        vals = [rnd.choice([0, 1, rnd.randrange(2 ** 32), rnd.randrange(2 ** 63), rnd.randrange(2 ** 70)])
                for _ in range(rnd.randrange(1, 5))]
        e = seed_entropy(*vals)
        assert decode(e) == tuple(vals)
        assert e[-1] != 0 and all(0 <= w < 2 ** 32 for w in e)


def state(*values):
    return tuple(np.random.SeedSequence(seed_entropy(*values)).generate_state(4))


def test_a_seed_split_into_words_is_not_another_seed_with_keys():
    """The collision of the old lists: seed 5 + 10^6 2^32 at cell (2, 0) read as seed 5 at cell (1, 2)."""
    old_a = np.random.SeedSequence([5, cell_key(1.0), cell_key(2.0)]).generate_state(4)
    old_b = np.random.SeedSequence([5 + (10 ** 6 << 32), cell_key(2.0), cell_key(0.0)]).generate_state(4)
    assert (old_a == old_b).all()          # the bug: one stream for two seeds
    assert state(5, cell_key(1.0), cell_key(2.0)) != state(5 + (10 ** 6 << 32), cell_key(2.0), cell_key(0.0))


def test_streams_of_many_seeds_and_cells_are_distinct():
    seeds = [0, 1, 2, 2 ** 31, 2 ** 32, 2 ** 32 + 1, 5 + (10 ** 6 << 32), SEED_MAX]
    cells = [(0.0, 0.0), (1.0, 2.0), (2.0, 0.0), (12.0, 180.0), (0.25, 5.0)]
    seen = {}
    for s in seeds:
        for t, b in cells:
            key = state(s, cell_key(t), cell_key(b))
            assert key not in seen, (s, t, b, seen.get(key))
            seen[key] = (s, t, b)
