"""Age of reused rollout features: a static rollout schedule reuses the episode's first call, a
rotating schedule refreshes every slot; Summary.rollout_ages matches what the cache really served."""
import pytest
import torch

import tts

STEPS = 8


class Marker(torch.nn.Module):
    """One block, one branch whose delta is the number of the call that computed it."""

    def __init__(self):
        super().__init__()
        self.call = 0

    def forward(self, x):
        return x + self.delta(x)

    def delta(self, x):
        return torch.full_like(x, float(self.call))


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.blk = Marker()

    def forward(self, x, t):
        return self.blk(x)


SPEC = tts.BlockSpec(family="marker", branches=(tts.BranchSpec("delta", kind="ff"),),
                     forward=lambda block, run, x: x + run(0, block.delta, x))


def run_episode(plan, calls: int):
    """One episode of ``calls`` sampling calls; returns the summary and, per call and step, the call
    whose branch output was used (read back from the block's output)."""
    model = Net()
    served = []
    with tts.accelerate(model, ("rollout",), plan=plan, blocks={"blk": SPEC}) as acc:
        acc.new_rollout()
        for c in range(calls):
            model.blk.call = c
            acc.new_call()
            x = torch.zeros(1, 3)
            served.append([int(model(x, torch.tensor(STEPS - k))[0, 0]) for k in range(STEPS)])
        return acc.summary(), served


def served_ages(served, summary):
    """Ages of the rollout decisions, from what the model actually returned."""
    out = []
    for c, (row, call) in enumerate(zip(served, summary.calls)):
        d = call.decisions()[:, 0, 0]
        out += [c - row[k] for k in range(STEPS) if d[k] == tts.plans.ROLLOUT]
    return out


def test_a_static_rollout_schedule_reuses_the_first_call_of_the_episode():
    summary, served = run_episode(tts.plans.uniform(0.75, "rollout"), calls=5)
    ages = summary.rollout_ages()
    assert sorted(ages.tolist()) == sorted(served_ages(served, summary))
    # the reused steps never compute: at call c their features come from call 0
    assert all(row[k] == 0 for row, call in zip(served, summary.calls) for k in range(STEPS)
               if call.decisions()[k, 0, 0] == tts.plans.ROLLOUT)
    stats = summary.rollout_age_stats()
    assert stats["max_calls"] == 4 and stats["fraction_previous_call"] == pytest.approx(1 / 4)
    assert summary.to_dict()["rollout_age"] == stats


def test_a_rotating_schedule_refreshes_every_slot_within_its_period():
    summary, served = run_episode(tts.plans.rotating(0.75, "rollout"), calls=12)
    ages = summary.rollout_ages()
    assert sorted(ages.tolist()) == sorted(served_ages(served, summary))
    assert int(ages.max()) <= 4  # one compute every 4 steps, moved by one step per call
    sparse = [c for c in summary.calls if not c.dense]
    # step 0 always computes; the rest of the call keeps the static schedule's sparsity
    assert all(abs(summary.sparsity_of(c) - 6 / 8) <= 1 / 8 for c in sparse)
    # the compute steps move: over 4 calls every step computes at least once
    computed = torch.stack([c.decisions()[:, 0, 0] == tts.plans.COMPUTE for c in sparse[:4]]).any(0)
    assert bool(computed.all())


def test_rotating_needs_whole_step_directions_and_reports_itself():
    with pytest.raises(ValueError, match="timestep or rollout"):
        tts.plans.rotating(0.9, "forward")
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        tts.plans.rotating(1.0)
    assert tts.plans.rotating(0.9).describe() == "rotating(sparsity=0.9, rollout)"


def test_no_rollout_direction_no_ages():
    model = Net()
    with tts.accelerate(model, ("timestep",), plan=tts.plans.uniform(0.5, "timestep"), blocks={"blk": SPEC}) as acc:
        for k in range(STEPS):
            model(torch.zeros(1, 3), torch.tensor(STEPS - k))
        assert acc.summary().rollout_ages().numel() == 0
        assert "rollout_age" not in acc.summary().to_dict()


def test_derived_schedule_reuses_rollout_early_and_keeps_its_compute_steps():
    from derive_schedule import derive

    doc = {"grid": ["CC", "TT", "TT", "CC", "TT", "TT"], "directions": ["timestep"], "sparsity": 0.5}
    out = derive(doc, "rollout", 3)
    assert out["grid"] == ["CC", "RR", "RR", "CC", "TT", "TT"]
    assert out["directions"] == ["timestep", "rollout"]
    assert derive(doc, "rollout", 1)["grid"] == doc["grid"]  # nothing reused before step 1
    with pytest.raises(ValueError, match="--until must be in 1..6"):
        derive(doc, "rollout", 7)
