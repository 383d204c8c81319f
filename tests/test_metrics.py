"""Metrics against hand-computed small cases and the paper's chi-square bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.analysis.metrics import (
    nees,
    nees_bounds,
    pose_errors,
    rmse_curve,
    share_inside,
    summarize_filter,
)


@pytest.mark.parametrize(
    "runs, lo, hi", [(20, 2.02, 4.17), (50, 2.36, 3.72)], ids=["N20-paper", "N50"]
)
def test_chi_square_bounds_match_the_paper(runs, lo, hi):
    # Exact N = 20 values are [2.024, 4.165]; the paper prints them as [2.02, 4.17].
    got = nees_bounds(runs)
    assert got[0] == pytest.approx(lo, abs=0.006)
    assert got[1] == pytest.approx(hi, abs=0.006)


def test_pose_errors_wrap_heading():
    e = pose_errors(np.array([[1.0, 2.0, math.pi - 0.1]]), np.array([[0.5, 2.5, -math.pi + 0.1]]))
    np.testing.assert_allclose(e, [[0.5, -0.5, -0.2]], atol=1e-12)


def test_nees_by_hand():
    e = np.array([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0]])
    P = np.stack([np.diag([1.0, 4.0, 0.25]), np.eye(3)])
    np.testing.assert_allclose(nees(e, P), [1.0 + 1.0 + 1.0, 0.0])
    Pc = np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    e1 = np.array([1.0, 1.0, 0.0])
    assert nees(e1[None], Pc[None])[0] == pytest.approx(e1 @ np.linalg.inv(Pc) @ e1)


def test_rmse_curve_by_hand():
    err = np.array([[3.0, 0.0], [4.0, 2.0]])
    np.testing.assert_allclose(rmse_curve(err), [math.sqrt(12.5), math.sqrt(2.0)])


def test_share_inside_is_strict():
    assert share_inside(np.array([1.0, 2.0, 3.0, 4.0]), 1.0, 4.0) == 0.5


def test_summary_by_hand_and_diverged_runs_left_out():
    pos = np.array([[1.0, 1.0], [3.0, 3.0], [np.nan, np.nan]])
    head = np.array([[0.1, 0.1], [0.1, 0.1], [np.nan, np.nan]])
    nees_ = np.array([[3.0, 30.0], [3.0, 30.0], [np.nan, np.nan]])
    rec = summarize_filter(pos, head, nees_, np.array([False, False, True]))
    assert rec["runs"] == 3 and rec["diverged"] == 1 and rec["runs_used"] == 2
    assert rec["rmse_pos"] == pytest.approx(math.sqrt(5.0))
    assert rec["rmse_heading"] == pytest.approx(0.1)
    assert rec["anees"] == pytest.approx(16.5)
    lo, hi = nees_bounds(2)
    assert (rec["nees_lo"], rec["nees_hi"]) == (lo, hi)
    assert rec["nees_in_bounds"] == 0.5
