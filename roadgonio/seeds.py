"""Seeds: the range a user may give, and how a seed reaches the random generators, written once.

* A user's seed is a whole number 0 <= seed <= :data:`SEED_MAX` = 2^63 - 1 (not a bool, not a
  float, not text): :func:`check_seed` enforces it wherever a seed enters (the API, the command
  line, a backend's settings, a design study). Mitsuba's own samplers take a 32-bit seed, so
  ``roadgonio render`` accepts 0 <= seed <= :data:`MITSUBA_SEED_MAX` and says so.
* The full seed reaches the generator: numpy generators are seeded by
  ``SeedSequence(seed_entropy(seed, *keys))``, where the keys say which stream of the run it is (a
  cell, a pass, a replicate...). :func:`seed_entropy` is one-to-one: two different (seed, keys)
  give two different entropy lists, so two different seeds never give the same random numbers,
  not even for different cells. (A list ``[seed, key, ...]`` is not: numpy splits a seed >= 2^32
  into 32-bit words and ignores trailing zero words, so ``[5 + 10^6 * 2^32, 2 10^6, 0]`` and
  ``[5, 10^6, 2 10^6]`` were one stream.)
* :func:`point_seed` gives design point k of a root seed its own seed in the full range: for a
  fixed k it is a bijection of the roots (two different roots never give point k the same seed)
  and for a fixed root a bijection of the points (no two points share a seed).
"""
from __future__ import annotations

import numbers

from roadgonio.errors import InputError

#: Seeds a user may give: whole numbers 0 <= seed <= SEED_MAX.
SEED_MAX = 2 ** 63 - 1
#: The largest seed of a Mitsuba sampler (``mi.render(seed=...)`` is a 32-bit unsigned integer).
MITSUBA_SEED_MAX = 2 ** 32 - 1
_MASK63 = SEED_MAX


def check_seed(seed, field: str = "seed", maximum: int = SEED_MAX) -> int:
    """A seed as given by a user: a whole number 0 <= seed <= ``maximum`` (not a bool, not a
    float), returned as int; the full value reaches the generators (module docstring)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise InputError(f"expected a whole number >= 0 as the seed, got {seed!r}", field=field)
    s = int(seed)
    if not 0 <= s <= maximum:
        top = "2^63 - 1" if maximum == SEED_MAX else ("2^32 - 1: Mitsuba's samplers take a 32-bit seed"
                                                      if maximum == MITSUBA_SEED_MAX else str(maximum))
        raise InputError(f"expected a whole number >= 0 (at most {top}) as the seed, got {s}", field=field)
    return s


def seed_entropy(seed: int, *keys: int) -> list[int]:
    """The entropy of ``numpy.random.SeedSequence`` for stream ``keys`` of seed ``seed``: one-to-one
    in (seed, keys) (module docstring). Every value (whole numbers >= 0 of any size) is written as
    its count of 32-bit words followed by the words, and the list ends with the number of values
    (never 0, so no trailing zero word is dropped)."""
    out: list[int] = []
    for v in (seed, *keys):
        v = int(v)
        if v < 0:
            raise ValueError(f"seed_entropy takes whole numbers >= 0, got {v}")
        words = []
        while True:
            words.append(v & 0xFFFFFFFF)
            v >>= 32
            if not v:
                break
        out += [len(words), *words]
    out.append(1 + len(keys))
    return out


def _mix63(x: int) -> int:
    """A bijection of [0, 2^63): xor-shifts and multiplications by odd constants modulo 2^63 (each
    step invertible), so that nearby inputs give unrelated outputs."""
    x &= _MASK63
    x ^= x >> 31
    x = (x * 0x5DEECE66DA3B7F1) & _MASK63
    x ^= x >> 29
    x = (x * 0x2545F4914F6CDD1D) & _MASK63
    x ^= x >> 32
    return x


def point_seed(root: int, k: int) -> int:
    """The seed of design point ``k`` (0 <= k < 2^63) of root seed ``root``, in the full range
    0 ... 2^63 - 1: ``mix(mix(root) xor k)`` with ``mix`` a bijection, so point k of two different
    roots never shares a seed and no two points of one root do (module docstring)."""
    root, k = check_seed(root), int(k)
    if not 0 <= k <= SEED_MAX:
        raise ValueError(f"point index out of range: {k}")
    return _mix63(_mix63(root) ^ k)


def cell_key(value: float) -> int:
    """A cell coordinate (tan eps, or beta in degrees; >= 0) as a stream key of
    :func:`seed_entropy`: in millionths, so every cell a user can name has its own stream."""
    return int(round(float(value) * 1e6))
