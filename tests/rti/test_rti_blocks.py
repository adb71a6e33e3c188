"""Fits larger than memory (mitsuba_powder.rti.blocks): the memory budget, the pixels in
blocks that partition the mask in row-major order, the blocks' maps and diagnostics put
together (as the tiles' are). The fits of blocks themselves are compared bit for bit with a
fit in one block in tests/rti/test_rti_engine.py."""

from __future__ import annotations

import re

import numpy as np
import pytest

from mitsuba_powder.rti.blocks import (
    LANE_BYTES,
    LANE_SHARE,
    MEMORY_GB_MAX,
    OBSERVATION_BYTES,
    SUMMED,
    block_pixels,
    check_memory,
    default_memory_gb,
    lanes_within,
    merge_block,
    merge_fit_settings,
    pixel_blocks,
)
from mitsuba_powder.rti.result import MapsResult


def test_the_budget_is_shared_between_numpy_and_dr_jit():
    gib = 2**30
    assert block_pixels(1.0, 50) == int((1 - LANE_SHARE) * gib / (OBSERVATION_BYTES * 50))
    assert lanes_within(1.0, 1 << 40) == int(LANE_SHARE * gib / LANE_BYTES)
    assert lanes_within(1.0, 1000) == 1000 and lanes_within(1e-12, 1000) == 1
    assert block_pixels(1e-12, 50) == 1
    assert 0.25 <= default_memory_gb() <= MEMORY_GB_MAX
    assert check_memory(None) == default_memory_gb()
    assert check_memory(2) == 2.0
    for bad, message in ((0, "memory_gb = 0 is out of range; valid range is [0.015625, inf) GiB"),
                         (float("inf"), "memory_gb = inf is out of range"),
                         ("lots", "memory_gb = 'lots' is not a number")):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_memory(bad)


def test_blocks_partition_the_mask_in_row_major_bands():
    rng = np.random.default_rng(0)
    mask = rng.random((30, 40)) < 0.6
    memory = 1e-4  # GiB: a few hundred pixels a block at 10 lights
    size = block_pixels(memory, 10)
    blocks = pixel_blocks(mask, 10, memory, gains_fitted=False)
    assert len(blocks) == int(np.ceil(mask.sum() / size)) > 2
    np.testing.assert_array_equal(np.sum(blocks, axis=0), mask)  # each pixel once
    assert all(b.sum() <= size for b in blocks)
    firsts = [np.flatnonzero(b)[0] for b in blocks]
    lasts = [np.flatnonzero(b)[-1] for b in blocks]
    assert all(last < first for last, first in zip(lasts, firsts[1:]))  # bands in order
    # the gains couple every pixel: one block while they are fitted
    assert len(pixel_blocks(mask, 10, memory, gains_fitted=True)) == 1


def _result(mask: np.ndarray, value: float, settings: dict) -> MapsResult:
    h, w = mask.shape
    nan = np.full((h, w), np.nan, np.float32)
    put = np.where(mask, np.float32(value), nan)
    return MapsResult(normals=np.repeat(put[..., None], 3, -1),
                      albedo=np.repeat(put[..., None], 3, -1), maps={"g": put.copy()},
                      settings={}, residual_rms=put.copy(), gains=np.ones(2),
                      used=np.broadcast_to(mask, (2, h, w)).copy(), free=["albedo"], mask=mask,
                      fit_settings=settings)


def test_blocks_and_their_diagnostics_are_put_together():
    a = np.zeros((2, 3), bool)
    a[0] = True
    b = ~a
    one = {"free": ["albedo"], "evaluations": 10, "chunks": 1, "underdetermined_pixels": 0,
           "iterations_last_round": 7, "stages": ["x"]}
    two = {**one, "evaluations": 5, "chunks": 2, "underdetermined_pixels": 3,
           "iterations_last_round": 9}
    merged = merge_block(_result(a, 1.0, one), _result(b, 2.0, two))
    np.testing.assert_array_equal(merged.albedo[..., 0], np.where(a, 1.0, 2.0))
    np.testing.assert_array_equal(merged.maps["g"], np.where(a, 1.0, 2.0))
    assert merged.used.all()
    assert merged.fit_settings == {**one, "evaluations": 15, "chunks": 3,
                                   "underdetermined_pixels": 3, "iterations_last_round": 9}
    assert list(merged.fit_settings) == list(one)  # the first part's keys, in their order
    assert set(SUMMED) == {"evaluations", "chunks", "underdetermined_pixels",
                           "pixels_at_cap_last_round"}
    capped = merge_fit_settings([{**one, "pixels_at_cap_last_round": 2, "rounds_at_cap": 1},
                                 {**two, "pixels_at_cap_last_round": 3, "rounds_at_cap": 2}])
    assert capped["pixels_at_cap_last_round"] == 5 and capped["rounds_at_cap"] == 2
    three = merge_fit_settings([one, two, two])
    assert three["evaluations"] == 20 and three["iterations_last_round"] == 9
