"""tts.plans.Plan declares the whole protocol the engine calls; a user plan overrides only what it needs."""
import pytest
import torch

import tts
from conftest import TorchStack, randomize, tiny_dp, torch_stack_inputs
from tts.plans import COMPUTE, TIMESTEP, Plan

pytestmark = pytest.mark.usefixtures("one_thread")

PROTOCOL = ("uses", "codes", "soft", "wants_probe", "timing", "macs_per_sample", "reads_condition", "may_reuse",
            "bind", "observe", "begin_call", "step", "soft_step", "record_probe", "select_tokens", "describe")


def test_plan_declares_the_engine_protocol_with_defaults():
    missing = [name for name in PROTOCOL if not hasattr(Plan, name)]
    assert not missing, f"Plan does not declare {missing}"

    class OnlyStep(Plan):
        def step(self, k, batch):
            return torch.zeros(1, self.num_branches, dtype=torch.int8)

    plan = OnlyStep()
    assert not plan.soft and not plan.wants_probe and not plan.reads_condition
    assert dict(plan.timing) == {} and plan.macs_per_sample == 0.0 and list(plan.codes) == [COMPUTE]
    assert plan.observe(torch.zeros(1, 2, 3, 4), dense=False) is None
    assert plan.record_probe(0, torch.zeros(1, 3)) is None
    with pytest.raises(NotImplementedError, match="soft"):
        plan.soft_step(1)
    with pytest.raises(NotImplementedError, match="token"):
        plan.select_tokens(0, 0, 1, torch.zeros(1, 3, 4))
    # the learned pruner's plan and the token-refresh plans are plans of the same protocol
    assert tts.PrunerPlan.reads_condition.fget is Plan.reads_condition.fget
    assert tts.tokens.toca(3, 0.5).wants_probe and not tts.tokens.duca(4, 0.5).wants_probe


class ConditionedPlan(Plan):
    """Reads the condition memory, reports time and MACs, reuses the timestep cache after step 0."""

    uses = frozenset({COMPUTE, TIMESTEP})
    macs_per_sample = 123.0

    def __init__(self):
        self.seen = []
        self.timing = {}

    def observe(self, memory, dense):
        self.seen.append((tuple(memory.shape), dense))
        self.timing = {"planner": 0.25}

    def step(self, k, batch):
        return torch.full((1, self.num_branches), TIMESTEP, dtype=torch.int8)


def test_engine_feeds_a_user_plan_the_condition_memory_and_records_its_cost():
    from tts.adapters.diffusion_policy import sample_actions

    class Scheduler:  # what sample_actions needs of a scheduler, without diffusers
        timesteps = torch.tensor([40, 30, 20, 10])

        def step(self, out, t, x, generator=None):
            return type("Out", (), {"prev_sample": x - 0.1 * out})()

    model = randomize(tiny_dp()).eval()
    plan = ConditionedPlan()
    with tts.accelerate(model, ("timestep",), plan=plan) as acc:
        sample_actions(model, torch.randn(3, 2, 7), Scheduler(), fast=False)  # condition encoded per step
        assert plan.seen == []
        memory = model.condition_memory(Scheduler.timesteps, torch.randn(3, 2, 7))
        for i, t in enumerate(Scheduler.timesteps):
            model(torch.randn(3, 6, 5), t, None, memory=memory[:, i])
        record = acc.summary().calls[-1]
    assert plan.seen == [((3, 4, 3, 32), False)]
    assert record.timing["planner"] == 0.25 and "encoder" in record.timing
    assert record.pruner_macs == 123.0 * 3
    assert int((record.decisions() == TIMESTEP).sum()) == 3 * 3 * 9  # steps 1..3, 3 samples, 9 branches


def test_plan_reading_the_condition_needs_a_model_that_declares_it():
    with pytest.raises(ValueError, match="reads the condition memory.*Target.condition"):
        tts.accelerate(TorchStack("decoder", True), ("timestep",), plan=ConditionedPlan())


def test_static_plan_on_a_model_without_condition_still_runs():
    model = randomize(TorchStack("decoder", True)).eval()
    x, t, mem = torch_stack_inputs(2)
    with torch.no_grad(), tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2)) as acc:
        for k in range(4):
            model(x, t - k, mem)
    assert acc.summary().sparsity() == 0.5
