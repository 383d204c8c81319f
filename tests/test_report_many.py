"""The overview and the leaderboard stay readable with many filters: no two text labels overlap
(bounding boxes from the renderer), none is cut off by the figure's edge, and the ratio scale
gives a ratio of 1 one colour wherever it appears."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from anfekf_bench.report import plots, ranking, summary_figures
from anfekf_bench.report.report import Ratio, SummaryRow


def many_rows(filters: int, scenarios: int, seed: int = 3) -> list[SummaryRow]:
    """Summary rows of `filters` filters (the last is the oracle) in `scenarios` scenarios, with
    ratios from 0.98 to 40 and their intervals: what a zoo's report holds."""
    rng = np.random.default_rng(seed)
    rows = []
    names = [f"zoo-filter-{i:02d}" for i in range(filters - 1)] + ["ekf-oracle"]
    for s in range(scenarios):
        for i, name in enumerate(names):
            oracle = name == "ekf-oracle"
            r = 1.0 if oracle else float(np.exp(rng.uniform(math.log(0.98), math.log(40))))
            ratio = None if oracle else Ratio(r, r / 1.05, r * 1.05, 50)
            rows.append(
                SummaryRow(
                    scenario=f"scenario_{s}", filter=name,
                    kind="ekf-oracle" if oracle else ("ekf" if i == 0 else "anfekf"),
                    runs=50, runs_used=50, rmse_pos=0.1 * r, rmse_heading_deg=1.0,
                    anees=3.0 * r, nees_in_bounds=float(rng.uniform(0.5, 1.0)), nees_lo=2.5,
                    nees_hi=3.5, vs_ekf=math.nan, vs_oracle=r, rmse_vs_oracle=ratio,
                    anees_vs_oracle=ratio,
                )
            )  # fmt: skip
    return rows


def drawn_texts(fig) -> list:
    """(text, bounding box) of every text the renderer draws."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    texts = list(fig.texts)  # the suptitle is one of them
    for legend in fig.legends:
        texts += [*legend.get_texts(), legend.get_title()]
    for ax in fig.axes:
        if not ax.get_visible():
            continue
        texts += [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label]
        texts += list(ax.texts)
        if ax.get_legend():
            texts += [*ax.get_legend().get_texts(), ax.get_legend().get_title()]
        for axis in (ax.xaxis, ax.yaxis):
            for tick in axis._update_ticks():  # the ticks in view: the ones drawn
                texts += [tick.label1, tick.label2]
    shown = [t for t in texts if t is not None and t.get_visible() and t.get_text().strip()]
    shown = list({id(t): t for t in shown}.values())
    return [(t.get_text(), t.get_window_extent(renderer)) for t in shown]


def assert_readable(fig) -> None:
    boxes = drawn_texts(fig)
    assert boxes
    page = fig.bbox
    for text, box in boxes:  # nothing cut off at the figure's edge (a clipped title)
        assert box.x0 >= page.x0 - 1 and box.x1 <= page.x1 + 1, text
        assert box.y0 >= page.y0 - 1 and box.y1 <= page.y1 + 1, text
    for i, (a, box_a) in enumerate(boxes):
        for b, box_b in boxes[i + 1 :]:
            # a little slack: boxes of neighbouring glyph lines touch at their padding
            overlap_w = min(box_a.x1, box_b.x1) - max(box_a.x0, box_b.x0)
            overlap_h = min(box_a.y1, box_b.y1) - max(box_a.y0, box_b.y0)
            assert overlap_w <= 0.5 or overlap_h <= 0.5, f"{a!r} overlaps {b!r}"


@pytest.mark.parametrize(
    ("filters", "scenarios"), [pytest.param(30, 6, marks=pytest.mark.slow), (18, 2), (3, 1)]
)
def test_the_leaderboard_has_no_overlapping_labels(filters, scenarios):
    fig = summary_figures.leaderboard_figure(many_rows(filters, scenarios))
    assert_readable(fig)


@pytest.mark.parametrize(
    ("filters", "scenarios"), [pytest.param(30, 6, marks=pytest.mark.slow), (18, 2), (3, 1)]
)
def test_the_overview_has_no_overlapping_labels(filters, scenarios):
    rows = many_rows(filters, scenarios)
    with plots.palette([r.filter for r in rows]):
        fig = summary_figures.overview_figure(rows)
    assert_readable(fig)


def test_the_leaderboard_sorts_best_first_and_marks_cells():
    rows = many_rows(8, 3)
    fig = summary_figures.leaderboard_figure(rows)
    ax = fig.axes[0]
    names = [t.get_text() for t in ax.get_yticklabels()]
    median = {
        n: np.median([r.vs_oracle for r in rows if r.filter == n]) for n in {r.filter for r in rows}
    }
    assert names == sorted(names, key=lambda n: median[n])
    texts = {t.get_gid(): t.get_text() for t in ax.texts}
    for r in rows:
        text = texts[f"leaderboard_value/{r.scenario}/{r.filter}"]
        assert text.endswith("•") == ranking.consistent(r)
    frames = {p.get_gid() for p in ax.patches if p.get_gid()}
    assert frames == set()  # no interval of many_rows includes 1 except ...
    rows[0] = rows[0].__class__(
        **{**rows[0].__dict__, "rmse_vs_oracle": Ratio(1.02, 0.99, 1.05, 50)}
    )
    ax = summary_figures.leaderboard_figure(rows).axes[0]
    assert {p.get_gid() for p in ax.patches if p.get_gid()} == {
        f"leaderboard_ci1/{rows[0].scenario}/{rows[0].filter}"
    }


def test_a_ratio_of_one_has_one_colour_everywhere():
    one = plots.ratio_colour(1.0)
    assert one[:3] == pytest.approx((0.97, 0.97, 0.97), abs=0.03)  # white: the centre
    # the same in every leaderboard, whatever the data's range
    for rows in (many_rows(5, 2, seed=1), many_rows(12, 4, seed=2)):
        rows = [r for r in rows if r.filter == "ekf-oracle"] + rows
        fig = summary_figures.leaderboard_figure(rows)
        image = fig.axes[0].get_images()[0]
        names = [t.get_text() for t in fig.axes[0].get_yticklabels()]
        i = names.index("ekf-oracle")
        assert tuple(image.to_rgba(image.get_array()[i, 0])) == pytest.approx(one)
    assert plots.ratio_colour(30.0) == plots.ratio_colour(300.0)  # the top end saturates
    assert plots.ratio_colour(1.5) != plots.ratio_colour(2.0)


@pytest.mark.parametrize("rows, inches", [(2, 1.6), (6, 3.0), (30, 8.0)])
def test_the_ratio_bars_tick_labels_never_touch(rows, inches):
    """The ratio colour bar keeps as many ticks as its drawn height fits: on a two-row heatmap
    (the drives' figure) the labels 1.5, 2 and 3 used to overlap."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, inches), layout="constrained")
    ax = fig.add_subplot()
    values = np.exp(np.random.default_rng(0).normal(0.0, 1.0, (rows, 11)))
    plots.ratio_colourbar(fig, plots.ratio_image(ax, values), ax, "ratio (log)")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    bar = fig.axes[-1]
    labels = [t for t in bar.get_yticklabels() if t.get_text()]
    boxes = sorted((t.get_window_extent(canvas.get_renderer()) for t in labels), key=lambda b: b.y0)
    assert all(lower.y1 <= upper.y0 for lower, upper in zip(boxes, boxes[1:], strict=False))
    texts = {t.get_text() for t in labels}
    assert {"1", "0.667", "30"} <= texts  # the reference and the scale's ends always
    if inches >= 8.0:
        assert len(texts) == len(plots.RATIO_TICK_PRIORITY)  # room for every tick
    else:
        assert len(texts) < len(plots.RATIO_TICK_PRIORITY)
