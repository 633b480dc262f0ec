"""eval/tables.py: the paired comparison with dense on the same test episodes."""
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "eval"))

from tables import paired_vs_dense  # noqa: E402


def run(outcomes: dict[int, bool]) -> dict:
    return {"episodes": [{"seed": s, "success": ok} for s, ok in outcomes.items()]}


def test_paired_difference_counts_discordant_episodes_on_common_seeds_only():
    dense = [run({1: True, 2: True, 3: False, 4: True})]
    mine = [run({1: True, 2: False}), run({3: True, 4: False, 99: True})]  # seed 99: no dense episode
    text = paired_vs_dense(mine, dense)
    assert text.startswith("-0.250 (") and text.endswith("on 4; 2 / 1")
    lo, hi = (float(x) for x in text.split("(")[1].split(")")[0].split(", "))
    assert lo < -0.25 < hi


def test_identical_outcomes_give_a_zero_width_interval_and_no_overlap_is_reported():
    dense = [run({1: True, 2: False})]
    assert paired_vs_dense([run({1: True, 2: False})], dense) == "+0.000 (+0.000, +0.000) on 2; 0 / 0"
    assert paired_vs_dense([run({5: True})], dense) == "no common episodes"
    with pytest.raises(KeyError):
        paired_vs_dense([{"episodes": [{"seed": 1}]}], dense)
