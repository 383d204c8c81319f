"""The tables' fast paths give what the plain pandas forms give (issue 37)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from anfekf_bench.analysis.tables import STEP_COLUMNS, _as_str, filter_arrays, parquet_frame


def _steps(runs: int = 3, steps: int = 4, names=("ekf", "anfekf")) -> pd.DataFrame:
    rng = np.random.default_rng(0)
    n = len(names) * runs * steps
    cols = {c: rng.normal(size=n) for c in STEP_COLUMNS}
    cols["scenario"] = pd.Categorical.from_codes(np.zeros(n, dtype=np.int8), ["s"])
    cols["filter"] = pd.Categorical.from_codes(
        np.repeat(np.arange(len(names)), runs * steps), names
    )
    cols["run"] = np.tile(np.repeat(np.arange(runs, dtype=np.int32), steps), len(names))
    cols["step"] = np.tile(np.arange(1, steps + 1, dtype=np.int32) * 8, len(names) * runs)
    cols["diverged"] = np.zeros(n, dtype=bool)
    return pd.DataFrame(cols, columns=STEP_COLUMNS)


def _plain_filter_arrays(steps: pd.DataFrame, name: str) -> dict[str, np.ndarray]:
    """filter_arrays as it was written with pandas (before issue 37)."""
    sub = steps[steps["filter"] == name].sort_values(["run", "step"])
    runs = sub["run"].unique()
    n = len(sub) // max(len(runs), 1)
    out = {"run": runs, "step": sub["step"].to_numpy()[:n], "t": sub["t"].to_numpy()[:n]}
    for col in ("pos_err", "heading_err", "nees", "R_rr", "R_bb", "Q_vv", "Q_gg"):
        out[col] = sub[col].to_numpy().reshape(len(runs), n)
    out["diverged"] = sub["diverged"].to_numpy().reshape(len(runs), n)[:, 0]
    return out


def test_filter_arrays_equal_the_pandas_form_in_any_row_order() -> None:
    steps = _steps()
    for frame in (steps, steps.sample(frac=1, random_state=3), parquet_frame(steps)):
        for name in ("ekf", "anfekf"):
            got, want = filter_arrays(frame, name), _plain_filter_arrays(frame, name)
            assert got.keys() == want.keys()
            for key in want:
                assert got[key].dtype == want[key].dtype, key
                np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_key_columns_as_text_equal_astype_str() -> None:
    cat = pd.Series(pd.Categorical.from_codes([1, 0, 1, 1], ["ekf", "anfekf"]), index=[5, 6, 7, 8])
    with_nan = pd.Series(pd.Categorical(["ekf", None, "ekf"]))
    for col in (cat, with_nan, pd.Series(["a", "b"])):
        got, want = _as_str(col), col.astype(str)
        assert got.dtype == want.dtype
        pd.testing.assert_series_equal(got, want, check_names=False)


def test_in_key_order_is_whether_lexsort_would_leave_the_rows_as_they_are():
    from anfekf_bench.analysis.tables import in_key_order

    rng = np.random.default_rng(7)
    for _ in range(500):
        n = int(rng.integers(1, 9))
        keys = [rng.integers(0, 3, n) for _ in range(int(rng.integers(1, 4)))]
        stacked = np.stack(keys)
        unchanged = np.array_equal(stacked[:, np.lexsort(keys[::-1])], stacked)
        assert in_key_order(*keys) == unchanged, keys
        distinct = len({tuple(row) for row in stacked.T}) == n
        assert in_key_order(*keys, strict=True) == (unchanged and distinct), keys
    assert in_key_order(np.array([0, 0, 1]), np.array([2, 3, 0]))
    assert not in_key_order(np.array([0, 0, 1]), np.array([3, 2, 0]))  # the second key decides
    assert not in_key_order(np.array([1, 0]), np.array([0, 1]))  # the first key comes first
    assert not in_key_order(np.array([0, 0, 1]), np.array([2, 2, 0]), strict=True)  # a repeat
    assert in_key_order(np.array([0, 1, 1]), np.array([2, 2, 3]), strict=True)
