"""remove() restores the model; bad input gives clear errors, never a silent no-op."""
import pytest
import torch
import torch.nn as nn

import tts
from conftest import TorchStack, randomize, tiny_dit_diffusers, tiny_dp, tiny_official_dit, torch_stack_inputs
from helpers import run

pytestmark = pytest.mark.usefixtures("one_thread")  # small models: threads only add synchronisation


def _state(model):
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_remove_restores_model():
    model = randomize(TorchStack("decoder", True)).eval()
    args = torch_stack_inputs(2)
    ref, state = run(model, args), _state(model)
    keys_before = set(model.state_dict())
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2))
    assert "forward" in model.__dict__ and "forward" in model.layers[0].__dict__
    for k in range(3):
        run(model, (args[0], torch.full((2,), 9 - k), args[2]))
    assert set(model.state_dict()) == keys_before  # no buffers/parameters added
    acc.remove()
    acc.remove()  # idempotent
    assert all("forward" not in m.__dict__ for m in model.modules())
    assert all(not m._forward_hooks and not m._forward_pre_hooks for m in model.modules())
    assert torch.equal(run(model, args), ref)
    after = _state(model)
    assert all(torch.equal(state[k], after[k]) for k in state)
    # and it can be accelerated again
    with tts.accelerate(model, ("timestep",)):
        assert torch.equal(run(model, args), ref)
    assert "forward" not in model.__dict__


def test_context_manager_removes_on_error():
    model = randomize(TorchStack("decoder", True)).eval()
    with pytest.raises(RuntimeError, match="boom"):
        with tts.accelerate(model, ("timestep",)):
            raise RuntimeError("boom")
    assert all("forward" not in m.__dict__ for m in model.modules())


def test_second_accelerator_on_same_model_is_refused():
    model = TorchStack("decoder", True)
    acc = tts.accelerate(model, ("timestep",))
    with pytest.raises(RuntimeError, match="already accelerated"):
        tts.accelerate(model, ("timestep",))
    acc.remove()
    # a failure half-way through installing leaves nothing behind
    other = tts.accelerate(nn.Sequential(model.layers[2]), ("timestep",))
    with pytest.raises(RuntimeError, match="already accelerated"):
        tts.accelerate(model, ("timestep",))
    assert all("forward" not in m.__dict__ for m in (model, model.layers[0], model.layers[1]))
    other.remove()


@pytest.mark.parametrize("directions", [("backward",), ("forward", "space"), "sideways"])
def test_unknown_direction(directions):
    with pytest.raises(ValueError, match="unknown direction"):
        tts.accelerate(TorchStack("decoder", True), directions)


@pytest.mark.parametrize("sparsity", [1.0, -0.1, 1.5, float("nan")])
def test_bad_sparsity(sparsity):
    with pytest.raises(ValueError, match=r"sparsity must be in \[0, 1\)"):
        tts.accelerate(TorchStack("decoder", True), ("timestep",), sparsity=sparsity)
    with pytest.raises(ValueError, match="sparsity"):
        tts.plans.uniform(sparsity)


def test_unrecognised_model_says_how_to_declare_blocks():
    model = nn.Sequential(nn.Linear(4, 4), nn.ReLU(), nn.Linear(4, 4))
    with pytest.raises(TypeError, match="no recognisable transformer block.*BlockSpec"):
        tts.accelerate(model)
    with pytest.raises(ValueError, match="matches the block patterns"):
        tts.accelerate(model, blocks={"layers.*": lambda m: None})


def test_plan_of_wrong_shape():
    model = TorchStack("decoder", True, layers=3)  # 9 branches
    with pytest.raises(ValueError, match="plan has 8 branches per step but the model has 9"):
        tts.accelerate(model, ("timestep",), plan=tts.plans.from_tensor(torch.zeros(5, 8, dtype=torch.long)))
    with pytest.raises(ValueError, match="shape"):
        tts.plans.from_tensor(torch.zeros(5, dtype=torch.long))
    with pytest.raises(ValueError, match="codes must be in 0..3"):
        tts.plans.from_tensor(torch.full((5, 9), 4))
    with pytest.raises(TypeError, match="integer codes"):
        tts.plans.from_tensor(torch.zeros(5, 9))
    # too few steps / wrong batch only show at run time
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.from_tensor(["C" * 9, "T" * 9]))
    x, t, mem = torch_stack_inputs(1)
    with torch.no_grad():
        for k in range(2):
            model(x, torch.tensor([10 - k]), mem)
        with pytest.raises(IndexError, match="reached step 2 but the plan only has 2 steps"):
            model(x, torch.tensor([8]), mem)
    acc.remove()
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.from_tensor(torch.zeros(3, 2, 9, dtype=torch.long)))
    x, t, mem = torch_stack_inputs(2)
    with torch.no_grad(), pytest.raises(ValueError, match="decisions for 3 samples but the batch has 2"):
        model(x, torch.tensor([10, 10]), mem)
        model(x, torch.tensor([9, 9]), mem)
    acc.remove()


def test_plan_using_disabled_direction():
    with pytest.raises(ValueError, match=r"reuses along \['rollout'\].*not in directions"):
        tts.accelerate(TorchStack("decoder", True), ("forward", "timestep"),
                       plan=tts.plans.from_tensor(["C" * 9, "R" * 9]))
    with pytest.raises(ValueError, match="unknown decision letter"):
        tts.plans.from_tensor(["CX"])


@pytest.mark.parametrize("build", [tiny_dit_diffusers, tiny_official_dit])
def test_rollout_on_image_model(build):
    with pytest.raises(ValueError, match="not used in rollouts"):
        tts.accelerate(build())
    tts.accelerate(build(), ("forward", "timestep")).remove()


def test_batch_change_inside_episode_and_call():
    model = randomize(tiny_dp()).eval()
    acc = tts.accelerate(model, plan=tts.plans.every_n(2, "rollout"))
    cond1, cond2 = torch.randn(1, 2, 7), torch.randn(2, 2, 7)
    with torch.no_grad():
        for k in range(2):
            model(torch.randn(1, 6, 5), torch.tensor(5 - k), cond1)
        with pytest.raises(ValueError, match="within a rollout episode"):
            model(torch.randn(2, 6, 5), torch.tensor(5), cond2)
        acc.new_rollout()
        model(torch.randn(2, 6, 5), torch.tensor(5), cond2)
        with pytest.raises(ValueError, match="inside a sampling call"):
            model(torch.randn(1, 6, 5), torch.tensor(4), cond1)
    acc.remove()


def test_missing_timestep_needs_explicit_calls():
    class NoT(nn.Module):
        def __init__(self):
            super().__init__()
            self.layer = nn.TransformerEncoderLayer(8, 2, 16, batch_first=True)

        def forward(self, x):
            return self.layer(x)

    model = NoT().eval()
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2))
    with torch.no_grad(), pytest.raises(ValueError, match="new_call"):
        model(torch.randn(1, 3, 8))
    acc.new_call()
    with torch.no_grad():
        model(torch.randn(1, 3, 8))
        model(torch.randn(1, 3, 8))
    assert len(acc.summary().calls[-1].steps) == 2
    acc.remove()


def test_sparsity_and_plan_together_is_ambiguous():
    with pytest.raises(ValueError, match="either plan= or sparsity="):
        tts.accelerate(TorchStack("decoder", True), ("timestep",), plan=tts.plans.dense(), sparsity=0.5)
