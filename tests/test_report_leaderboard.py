"""The leaderboard ranks filters on the same scenarios only (a filter run in fewer is listed
apart, unranked, and says so), explains its grey cells, and marks a filter consistent only when
its ANEES is within the chi-square band too: a share of steps in bounds alone gave the dot to
sage-husa under wrong R with an ANEES of 292."""

from __future__ import annotations

import math

from anfekf_bench.report import summary_figures
from anfekf_bench.report.data import Ratio, SummaryRow
from anfekf_bench.report.ranking import consistent, rank
from anfekf_bench.report.tables import LEADERBOARD_CAPTION, leaderboard_table


def row(scenario: str, name: str, ratio: float, *, anees: float = 3.0, share: float = 0.95,
        kind: str = "anfekf") -> SummaryRow:  # fmt: skip
    oracle = name == "ekf-oracle"
    return SummaryRow(
        scenario=scenario, filter=name, kind="ekf-oracle" if oracle else kind, runs=50,
        runs_used=50, rmse_pos=0.1 * ratio, rmse_heading_deg=1.0, anees=anees,
        nees_in_bounds=share, nees_lo=2.5, nees_hi=3.5, vs_ekf=math.nan, vs_oracle=ratio,
        rmse_vs_oracle=None if oracle else Ratio(ratio, ratio / 1.1, ratio * 1.1, 50),
    )  # fmt: skip


def said(ax) -> str:
    """The figure's note below the cells, its wrapped lines joined."""
    return " ".join(ax.get_xlabel().split())


def paper_rows() -> list[SummaryRow]:
    """The paper's shape: ekf in four scenarios (1.00 in "correct", worse elsewhere),
    anfekf-q only in "correct" (0.99 there), anfekf in all four."""
    rows = []
    for scen, ekf, anfekf in (("correct", 1.0, 1.01), ("wrong_r", 2.2, 1.05),
                              ("wrong_q", 1.9, 1.3), ("consistency", 1.5, 1.04)):  # fmt: skip
        rows += [row(scen, "ekf", ekf, kind="ekf"), row(scen, "anfekf", anfekf)]
        if scen == "correct":
            rows.append(row(scen, "anfekf-q", 0.99))
        rows.append(row(scen, "ekf-oracle", 1.0))
    return rows


def test_a_filter_run_in_fewer_scenarios_is_unranked_and_listed_apart():
    rows = paper_rows()
    ranking = rank(rows)
    assert ranking.ranked == ["ekf-oracle", "anfekf", "ekf"]
    assert ranking.unranked == ["anfekf-q"] and ranking.ran_in["anfekf-q"] == 1
    assert ranking.scenarios == ["correct", "wrong_r", "wrong_q", "consistency"]
    ax = summary_figures.leaderboard_figure(rows).axes[0]
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels == ["ekf-oracle", "anfekf", "ekf", "anfekf-q (unranked: 1/4)"]
    assert [line.get_gid() for line in ax.lines] == ["leaderboard_unranked"]
    assert "every ranked filter ran" in said(ax) and "unranked" in said(ax)
    table = leaderboard_table(rows)
    assert [line[0].text for line in table.rows] == ["ekf-oracle", "anfekf", "ekf", "anfekf-q"]
    assert table.rows[-1][-1].text == "unranked (1/4 scenarios)"
    assert "every ranked filter ran" in table.caption


def test_the_ranking_is_over_the_scenarios_every_ranked_filter_ran():
    # b is better than a on the shared scenarios; a's extra scenario (where it is great) must
    # not lift it: the ranked filters are those that ran the most scenarios, on those only
    rows = [row("s1", "a", 2.0), row("s2", "a", 2.0), row("s3", "a", 0.9),
            row("s1", "b", 1.2), row("s2", "b", 1.2), row("s3", "b", 1.2),
            row("s1", "c", 0.5)]  # fmt: skip
    ranking = rank(rows)
    assert ranking.ranked == ["b", "a"] and ranking.unranked == ["c"]
    assert ranking.median == {"b": 1.2, "a": 2.0}


def test_grey_cells_are_explained_and_say_why():
    rows = paper_rows()
    diverged = row("wrong_r", "anfekf", math.nan)
    rows = [diverged if (r.scenario, r.filter) == ("wrong_r", "anfekf") else r for r in rows]
    ax = summary_figures.leaderboard_figure(rows).axes[0]
    texts = {t.get_gid(): t.get_text() for t in ax.texts}
    assert texts["leaderboard_none/wrong_r/anfekf-q"] == "-"  # not run
    assert texts["leaderboard_none/wrong_r/anfekf"] == "n/a"  # every run diverged
    assert "grey: no value" in said(ax)
    assert "grey" in LEADERBOARD_CAPTION and "not run" in LEADERBOARD_CAPTION
    # a cell with no value counts as the worst in the median: anfekf drops below ekf? no:
    # median of (1.01, inf, 1.3, 1.04) is 1.17, still above ekf's 1.7
    assert rank(rows).ranked == ["ekf-oracle", "anfekf", "ekf"]


def test_the_consistency_dot_needs_the_anees_within_the_chi_square_band():
    # sage-husa under wrong R: 93 % of steps in bounds but an ANEES of 292 (a few huge peaks)
    rows = [row("wrong_r", "sage-husa", 1.01, anees=292.0, share=0.93),
            row("wrong_r", "vb-r", 1.02, anees=3.1, share=0.93),
            row("wrong_r", "iae", 1.04, anees=3.0, share=0.6),
            row("wrong_r", "ekf-oracle", 1.0)]  # fmt: skip
    assert [consistent(r) for r in rows] == [False, True, False, True]
    ax = summary_figures.leaderboard_figure(rows).axes[0]
    texts = {t.get_gid(): t.get_text() for t in ax.texts}
    assert not texts["leaderboard_value/wrong_r/sage-husa"].endswith("•")
    assert texts["leaderboard_value/wrong_r/vb-r"].endswith("•")
    assert "chi-square band" in said(ax)
    table = leaderboard_table(rows)
    cells = {line[0].text: line[1].text for line in table.rows}
    assert not cells["sage-husa"].endswith("•") and cells["vb-r"].endswith("•")
    assert "chi-square band" in table.caption
