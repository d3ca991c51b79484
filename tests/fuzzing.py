"""Shared fuzzing helpers: seeded byte and structure mutations, and the check that a reader's
only outcomes are a result or a one-line :class:`rough_map.errors.RoughMapError`.

Every fuzz test draws seeds with hypothesis and turns each seed into one mutated input, so a
failure prints the seed that reproduces it::

    @FUZZ
    @given(seed=SEEDS)
    def test_read_cloud_survives(tmp_path_factory, seed):
        path = write_case(tmp_path_factory, "c.ply", mutate(BASE, seed))
        assert_bounded(read_cloud, path)

``FUZZ`` runs ``ROUGH_MAP_FUZZ_EXAMPLES`` cases per target (200 by default, the short pass CI
runs). The long pass is the same tests with a larger count, for example::

    ROUGH_MAP_FUZZ_EXAMPLES=5000 .venv/bin/python -m pytest -q -m fuzz -p no:randomly

Inputs that once broke a reader stay as plain regression tests next to the fuzz tests.
"""

from __future__ import annotations

import os
import random
import re
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from rough_map.errors import RoughMapError

__all__ = [
    "FUZZ",
    "MAX_MESSAGE",
    "SEEDS",
    "assert_bounded",
    "deep_json",
    "mutate",
    "write_case",
]

N_EXAMPLES = int(os.environ.get("ROUGH_MAP_FUZZ_EXAMPLES", "200"))
"""Cases per fuzz target: 200 in CI, more for the long pass run by hand."""

FUZZ = settings(
    max_examples=N_EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
"""hypothesis settings of every fuzz target (deterministic: the same cases on every run)."""

SEEDS = st.integers(min_value=0, max_value=2**32 - 1)

MAX_MESSAGE = 240
"""Longest error message accepted (the brief asks for about 200 characters)."""

_HUGE = [b"4294967295", b"18446744073709551615", b"99999999999999999999999", b"-1", b"0",
         b"1e308", b"nan", b"inf", b"-2147483648", b"2147483647"]  # fmt: skip


def mutate(data: bytes, seed: int) -> bytes:
    """One seeded mutation of ``data``: truncation, flipped, inserted, deleted, repeated or
    zeroed bytes, a number replaced by a huge, negative or non-finite one, or a few of these
    together. The same ``(data, seed)`` always gives the same bytes."""
    rng = random.Random(seed)
    out = bytearray(data)
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        if not out:
            out = bytearray(rng.randbytes(rng.randint(0, 64)))
            continue
        kind = rng.randrange(9)
        i = rng.randrange(len(out))
        if kind == 0:  # truncate
            del out[rng.randrange(len(out) + 1) :]
        elif kind == 1:  # flip a few bits
            for _ in range(rng.randint(1, 8)):
                out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
        elif kind == 2:  # random bytes over a run
            n = rng.randint(1, 32)
            out[i : i + n] = rng.randbytes(n)
        elif kind == 3:  # insert
            out[i:i] = rng.randbytes(rng.randint(1, 64))
        elif kind == 4:  # delete a run
            del out[i : i + rng.randint(1, 256)]
        elif kind == 5:  # repeat a run
            j = min(len(out), i + rng.randint(1, 512))
            out[j:j] = out[i:j] * rng.randint(1, 8)
        elif kind == 6:  # zero a run
            n = rng.randint(1, 64)
            out[i : i + n] = bytes(min(n, len(out) - i))
        elif kind == 7:  # a number (text) becomes a hostile one
            numbers = list(re.finditer(rb"-?\d+(\.\d+)?", bytes(out[:65536])))
            if numbers:
                m = rng.choice(numbers)
                out[m.start() : m.end()] = rng.choice(_HUGE)
        else:  # a 4- or 8-byte word (binary) becomes all ones or a huge count
            width = rng.choice((4, 8))
            value = rng.choice((2**31 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1, 0))
            out[i : i + width] = value.to_bytes(8, "little")[:width]
    return bytes(out)


def deep_json(depth: int, *, open_: str = "[", close: str = "]") -> str:
    """A JSON text nested ``depth`` levels deep (for nesting-bound tests)."""
    return open_ * depth + close * depth


def write_case(factory: pytest.TempPathFactory, name: str, data: bytes) -> Path:
    """Write one case to a fresh folder (hypothesis reuses fixtures across cases)."""
    path = factory.mktemp("fuzz", numbered=True) / name
    path.write_bytes(data)
    return path


def assert_bounded(
    fn: Callable[..., Any], *args: Any, max_bytes: int | None = None, **kwargs: Any
) -> Any:
    """Call ``fn``; its only allowed outcomes are a result or a :class:`RoughMapError` whose
    message is one line of at most :data:`MAX_MESSAGE` characters.

    With ``max_bytes`` the peak of traced allocations (numpy's included) must stay below it,
    to catch readers that trust a declared size. Returns the result, or the error.
    """
    if max_bytes is not None:
        tracemalloc.start()
    try:
        result: Any = fn(*args, **kwargs)
    except RoughMapError as err:
        message = str(err)
        assert "\n" not in message, f"multi-line error: {message!r}"
        assert len(message) <= MAX_MESSAGE, f"error of {len(message)} characters: {message!r}"
        assert message.isprintable(), f"unprintable characters in the error: {message!r}"
        result = err
    finally:
        if max_bytes is not None:
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
    if max_bytes is not None:
        assert peak <= max_bytes, f"{fn.__name__} allocated {peak} bytes (limit {max_bytes})"
    return result
