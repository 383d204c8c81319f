"""The bootstrap's time means of resampled run means, compiled (statistics._resampled_by_weights).

On numpy, g(block / den) is six passes over a (resamples, steps) block: the division, the square
root, the NaN mask, zeroing the NaN, counting the others, the sum. `time_means` does them in one
pass per row, with the same bits: division and square root are correctly rounded on either path,
and the sum is numpy's pairwise summation written out (`pairwise_sum`, numpy's
`pairwise_sum_DOUBLE`), added to the reduction's identity 0.0 as numpy's add.reduce does.
tests/test_statistics.py checks the bits against the numpy path on rows of every length numpy's
summation splits differently. The matrix product before it stays BLAS's.
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import is_compiled, maybe_njit

_PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE: below it, eight running sums; above, halves


@maybe_njit
def _block_sum(a, lo, n):
    """numpy's sum of n <= 128 values: in order below 8, else eight running sums."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = lo + 8
    stop = lo + n - n % 8
    while i < stop:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < lo + n:
        res += a[i]
        i += 1
    return res


@maybe_njit
def pairwise_sum(a, lo, n):
    """sum(a[lo : lo + n]) in numpy's order (pairwise_sum_DOUBLE of loops_utils.h): above 128
    values, the sum of the first `half` (n / 2 down to a multiple of 8) and of the rest. numpy
    recurses; this walks the same tree with a stack (numba's cache fails a caller of a
    recursive function: the second process to load it crashed)."""
    depth = 2 * 64
    todo_lo = np.empty(depth, np.int64)
    todo_n = np.empty(depth, np.int64)  # -1: add the two sums on top of `sums`
    sums = np.empty(depth)
    todo_lo[0], todo_n[0] = lo, n
    top, n_sums = 1, 0
    while top > 0:
        top -= 1
        at, size = todo_lo[top], todo_n[top]
        if size < 0:
            n_sums -= 1
            sums[n_sums - 1] = sums[n_sums - 1] + sums[n_sums]
        elif size <= _PAIRWISE_BLOCK:
            sums[n_sums] = _block_sum(a, at, size)
            n_sums += 1
        else:
            half = size // 2
            half -= half % 8
            todo_lo[top], todo_n[top] = at, -1  # after both halves
            todo_lo[top + 1], todo_n[top + 1] = at + half, size - half
            todo_lo[top + 2], todo_n[top + 2] = at, half  # first
            top += 3
    return sums[0]


@maybe_njit
def _kept(m, values, j):
    """values[j] = m, or 0.0 where m is NaN (left out of the mean, a zero in the sum, as in
    np.nanmean); 1 where kept, else 0."""
    ok = m == m
    values[j] = m if ok else 0.0
    return int(ok)


@maybe_njit
def time_means(block, den, divide, root, out):
    """out[i] = the time mean over the steps that have a value (not NaN) of m[i] = block[i]
    (divided by den[i] where `divide`; its square root where `root`): NaN where no step has
    one. statistics._time_mean_of's bits, for rows of any length."""
    rows, n = block.shape
    values = np.empty(n)
    for i in range(rows):
        b, d = block[i], den[i]
        count = 0
        # one loop per case, without a branch inside, so that the compiler can vectorise it
        if divide and root:
            for j in range(n):
                m = math.sqrt(b[j] / d[j])
                count += _kept(m, values, j)
        elif divide:
            for j in range(n):
                count += _kept(b[j] / d[j], values, j)
        elif root:
            for j in range(n):
                count += _kept(math.sqrt(b[j]), values, j)
        else:
            for j in range(n):
                count += _kept(b[j], values, j)
        out[i] = (0.0 + pairwise_sum(values, 0, n)) / count if count else math.nan
    return out


COMPILED: bool = is_compiled(time_means)
