"""The rasterizer's scratch pool: a buffer is lent to one caller at a time and reused once given back."""

from __future__ import annotations

import numpy as np

from reconstruction.render.scratch import ScratchPool


def test_given_back_buffer_serves_the_next_take_of_its_key():
    pool = ScratchPool()
    first = pool.take("pairs", 1000, np.float64)
    assert first.shape == (1000,) and first.dtype == np.float64
    pool.give("pairs", first)
    again = pool.take("pairs", 900, np.float64)
    assert np.shares_memory(first, again) and again.shape == (900,)


def test_a_lent_buffer_is_never_lent_twice():
    pool = ScratchPool()
    first = pool.take("pairs", 100, np.float64)
    second = pool.take("pairs", 100, np.float64)
    assert not np.shares_memory(first, second)
    other_key = pool.take("grads", 100, np.float64)
    pool.give("pairs", first)
    assert not np.shares_memory(pool.take("grads", 100, np.float64), first)
    assert not np.shares_memory(other_key, first)


def test_growth_dtype_change_and_reshaped_views():
    pool = ScratchPool()
    small = pool.take("pairs", 10, np.int16)
    pool.give("pairs", small)
    bigger = pool.take("pairs", 10_000, np.int16)
    assert bigger.shape == (10_000,) and not np.shares_memory(small, bigger)
    pool.give("pairs", bigger.reshape(100, 100))
    floats = pool.take("pairs", 10, np.float64)
    assert floats.dtype == np.float64 and not np.shares_memory(floats, bigger)
    pool.give("pairs", floats)
    pool.give("pairs", bigger)  # the larger of the two is the one kept
    assert np.shares_memory(pool.take("pairs", 5_000, np.int16), bigger)
    pool.clear()
    assert not np.shares_memory(pool.take("pairs", 5_000, np.int16), bigger)


def test_buffers_above_the_cap_are_not_kept():
    pool = ScratchPool(max_kept_bytes=8_000)
    big = pool.take("pairs", 2_000, np.float64)  # 16 kB with its growth room
    pool.give("pairs", big)
    assert not np.shares_memory(pool.take("pairs", 10, np.float64), big)
    small = pool.take("pairs", 500, np.float64)
    pool.give("pairs", small)
    assert np.shares_memory(pool.take("pairs", 500, np.float64), small)
