"""eval/oracle_headroom.py: candidate schedules and the oracle / cross-noise headroom arithmetic."""

import pytest
import torch

from oracle_headroom import headroom, neighbours


def test_neighbours_move_one_compute_step_and_keep_step_zero_and_the_budget():
    cands = neighbours([0, 10, 12], 16, [1, 4])
    assert cands[0] == [0, 10, 12]
    assert len({tuple(c) for c in cands}) == len(cands)
    for c in cands[1:]:
        assert c[0] == 0 and len(c) == 3 and len(set(c)) == 3 and max(c) < 16
        assert len(set(c) - {0, 10, 12}) == 1  # exactly one step moved
    # 10: 9, 11, 6, 14; 12: 11, 13, 8, 16 (out of range) -> 7 distinct moves
    assert sorted(map(tuple, cands[1:])) == sorted([(0, 9, 12), (0, 11, 12), (0, 6, 12), (0, 12, 14),
                                                    (0, 10, 11), (0, 10, 13), (0, 8, 10)])


def test_observation_driven_preferences_survive_a_new_noise_draw_and_noise_driven_ones_do_not():
    # 2 candidates x 4 calls; candidate 1 is better on calls 2, 3 on both draws (observation-driven)
    a = torch.tensor([[1.0, 1.0, 3.0, 3.0], [2.0, 2.0, 1.0, 1.0]])
    r = headroom(a, a.clone())
    assert r["searched_error"] == 2.0 and r["best_fixed_error"] == 1.5 and r["oracle_error"] == 1.0
    assert r["oracle_gain_over_best_fixed"] == pytest.approx(1 / 3)
    assert r["cross_noise_oracle_gain_over_best_fixed"] == pytest.approx(1 / 3)
    assert r["searched_is_best_fraction"] == 0.5
    # the per-call preference flips with the noise draw: the oracle's gain is not open to a pruner
    b = torch.tensor([[2.0, 2.0, 1.0, 1.0], [1.0, 1.0, 3.0, 3.0]])
    r = headroom(a, b)
    assert r["oracle_error"] == 1.0
    assert r["cross_noise_oracle_error"] > r["cross_noise_best_fixed_error"]
    with pytest.raises(ValueError, match="equal"):
        headroom(a, a[:, :2])
