"""Every shipped scenario's description agrees with its numbers: a description that says a noise
is "too large" or "too small" (for R, Qu, or one channel: range, bearing) names the direction its
own filter_noise / true_noise ratios have. configs/zoo/consistency.yaml said "both too large"
while its assumed bearing sigma is half the true one (its mismatch table: 0.500x)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
# the channels of each noise group, by their sigma keys
GROUPS = {
    "R": {"range": "sigma_range", "bearing": "sigma_bearing_deg"},
    "Q": {"v": "sigma_v", "gamma": "sigma_gamma_deg"},
}
ALIASES = {"Qu": "Q", "Q": "Q", "R": "R"}


def mismatch(doc: dict) -> dict[str, dict[str, float]]:
    """group -> channel -> assumed / true standard deviation (only channels given in both)."""
    true, assumed = doc.get("true_noise") or {}, doc.get("filter_noise") or {}
    return {
        group: {
            channel: assumed[key] / true[key]
            for channel, key in channels.items()
            if key in true and key in assumed
        }
        for group, channels in GROUPS.items()
    }


def direction_problems(description: str, ratios: dict[str, dict[str, float]]) -> list[str]:
    """The words of `description` about directions that its ratios contradict."""
    problems = []
    words = {"large": lambda r: r > 1, "small": lambda r: r < 1}
    channel_groups = {ch: g for g, chs in GROUPS.items() for ch in chs}
    # "too large in range", "too small in bearing": one channel
    for size, channel in re.findall(r"too (large|small) in (range|bearing)", description):
        ratio = ratios[channel_groups[channel]].get(channel)
        if ratio is not None and not words[size](ratio):
            problems.append(f"{channel} said too {size}, ratio {ratio:.3g}")
    # "both too large", "Qu too large", "R too small in both channels", "Wrong Q (too small)":
    # every mismatched channel of the group named in the description
    wholes = re.findall(r"too (large|small)(?! in (?:range|bearing))", description)
    named = {ALIASES[g] for g in re.findall(r"\b(Qu|Q|R)\b", description)}
    for size in wholes:
        for group in named or set(GROUPS):
            for channel, ratio in ratios[group].items():
                if ratio != 1 and not words[size](ratio):
                    problems.append(f"{group} {channel} said too {size}, ratio {ratio:.3g}")
    return problems


SCENARIO_FILES = sorted(CONFIGS.rglob("*.yaml"))


@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: str(p.relative_to(CONFIGS)))
def test_every_config_description_agrees_with_its_numbers(path):
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    description = " ".join(str(doc.get("description", "")).split())
    assert direction_problems(description, mismatch(doc)) == []


def test_the_check_finds_the_zoo_consistency_description_that_was_wrong():
    ratios = mismatch(yaml.safe_load((CONFIGS / "zoo" / "consistency.yaml").read_text()))
    assert ratios["R"] == {"range": 20.0, "bearing": 0.5}
    assert direction_problems("Wrong R, both too large (paper Figs. 13, 14)", ratios)
    assert direction_problems("Qu too small", {"R": {}, "Q": {"v": 10.0, "gamma": 6.0}})
    assert not direction_problems("Qu too large", {"R": {}, "Q": {"v": 10.0, "gamma": 6.0}})
