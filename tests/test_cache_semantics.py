"""Each direction returns exactly the cached tensor its definition (tts.cache) prescribes; skipped
branches never run.

A hand-built 3-block toy (2 branch kinds per block) logs every branch call (which sample rows it got,
what it returned) and every delta the engine handed back. A reference simulator, written from the
direction definitions and independent of the engine, replays the same decisions per sample and says
which logged tensor each returned delta must be.
"""
from __future__ import annotations

import random

import pytest
import torch
import torch.nn as nn

import tts
from tts.plans import COMPUTE, FORWARD, ROLLOUT, TIMESTEP

pytestmark = pytest.mark.usefixtures("one_thread")  # small models: threads only add synchronisation

KINDS = ("attn", "mlp")


class ToyBlock(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.a = nn.Linear(d, d)
        self.m = nn.Linear(d, d)

    def forward(self, x, ids):  # the model's own forward (used when nothing is hooked)
        x = x + torch.tanh(self.a(x))
        return x + torch.sin(self.m(x))


class Toy(nn.Module):
    def __init__(self, d=8, blocks=3):
        super().__init__()
        self.blocks = nn.ModuleList(ToyBlock(d) for _ in range(blocks))

    def forward(self, x, t, ids):
        for blk in self.blocks:
            x = blk(x, ids)
        return x


class Log:
    def __init__(self):
        self.computed = []  # (block, branch, ids tuple, output)
        self.returned = []  # (block, branch, delta)


def toy_spec(log: Log, index_of: dict) -> tts.BlockSpec:
    def forward(block, run, x, ids):
        bi = index_of[block]

        def a(h, i):
            out = torch.tanh(block.a(h))
            log.computed.append((bi, 0, tuple(i.tolist()), out))
            return out

        def m(h, i):
            out = torch.sin(block.m(h))
            log.computed.append((bi, 1, tuple(i.tolist()), out))
            return out

        d = run(0, a, x, ids)
        log.returned.append((bi, 0, d))
        x = x + d
        d = run(1, m, x, ids)
        log.returned.append((bi, 1, d))
        return x + d

    return tts.BlockSpec("toy", (tts.BranchSpec("a", "attn", ("a",)), tts.BranchSpec("m", "mlp", ("m",))), forward)


def make(seed=0):
    torch.manual_seed(seed)
    model = Toy().eval()
    log = Log()
    spec = toy_spec(log, {b: i for i, b in enumerate(model.blocks)})
    return model, log, spec


def reference(decisions_per_call, episode_starts, n_blocks, rollout):
    """Per sample: for each (call, step, block, branch) either ('computed', key) or ('reused', key)
    where key = (call, step, block, branch) of the computed output that must be returned."""
    nb = n_blocks * 2
    expected = []
    for s in range(decisions_per_call[0].shape[1]):
        R = {}
        per_sample = {}
        first = None
        for c, dec in enumerate(decisions_per_call):
            if c in episode_starts:
                R = {}
                first = True
            F, T = {}, {}
            for k in range(dec.shape[0]):
                for b in range(nb):
                    code = int(dec[k, s, b])
                    if k == 0 or (rollout and first):
                        code = COMPUTE
                    if code == ROLLOUT and (k, b) not in R:
                        code = COMPUTE  # R entry missing: computed instead
                    key = (c, k, b)
                    if code == COMPUTE:
                        per_sample[key] = ("computed", key)
                        F[b % 2], T[b], R[(k, b)] = key, key, key
                    else:
                        src = {FORWARD: F.get(b % 2), TIMESTEP: T.get(b), ROLLOUT: R.get((k, b))}[code]
                        assert src is not None
                        per_sample[key] = ("reused", src)
            first = False
        expected.append(per_sample)
    return expected


def run_calls(model, log, acc, calls, batch, steps, episode_starts):
    """Run the sampling calls; return {(sample, call, step, branch): returned row} and
    {(sample, call, step, branch): computed row}."""
    computed, returned = {}, {}
    ids = torch.arange(batch)
    for c in range(calls):
        if c in episode_starts:
            acc.new_rollout()
        x = torch.randn(batch, 4, 8, generator=torch.Generator().manual_seed(100 + c))
        for k in range(steps):
            log.computed.clear()
            log.returned.clear()
            with torch.no_grad():
                x = model(x, torch.tensor(steps - k), ids) * 0.5
            for bi, br, rows, out in log.computed:
                for j, s in enumerate(rows):
                    computed[(s, c, k, bi * 2 + br)] = out[j]
            for bi, br, d in log.returned:
                for s in range(batch):
                    returned[(s, c, k, bi * 2 + br)] = d[s]
    return computed, returned


@pytest.mark.parametrize("directions", [("forward", "timestep", "rollout"), ("forward",), ("timestep",), ("rollout",), ("forward", "rollout")])
@pytest.mark.parametrize("batch", [1, 3])
def test_directions_return_the_specified_cache(directions, batch):
    model, log, spec = make()
    steps, calls, nb = 5, 4, 6
    codes = [COMPUTE] + [tts.plans.DIRECTIONS[d] for d in directions]
    rng = random.Random(len(directions) * 10 + batch)
    dec = torch.tensor([[[rng.choice(codes) for _ in range(nb)] for _ in range(batch)] for _ in range(steps)],
                       dtype=torch.int8)  # [K, B, nb]; same decisions every call
    plan = tts.plans.from_tensor(dec.permute(1, 0, 2))
    episode_starts = {0, 3}
    acc = tts.accelerate(model, directions, plan=plan, blocks={"blocks.*": spec})
    computed, returned = run_calls(model, log, acc, calls, batch, steps, episode_starts)
    expected = reference([dec] * calls, episode_starts, 3, "rollout" in directions)
    n_computed = 0
    for s in range(batch):
        for (c, k, b), (what, src) in expected[s].items():
            got = returned[(s, c, k, b)]
            want = computed[(s,) + src]
            if what == "computed":
                n_computed += 1
            if batch == 1:
                assert torch.equal(got, want), (s, c, k, b, what, src)
            else:  # gathered sub-batches may round differently in the GEMM
                torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    # skipped branches are not run: the branch functions saw exactly the computing rows
    assert len(computed) == n_computed
    counts = acc.summary().counts()
    assert counts["compute"] == n_computed


def test_rollout_cache_persists_and_resets():
    model, log, spec = make()
    plan = tts.plans.from_tensor(torch.tensor([[COMPUTE, COMPUTE] * 3] + [[ROLLOUT, ROLLOUT] * 3] * 2))
    acc = tts.accelerate(model, ("rollout",), plan=plan, blocks={"blocks.*": spec})
    ids = torch.arange(1)
    with torch.no_grad():
        for call in range(3):
            for k in range(3):
                model(torch.randn(1, 4, 8), torch.tensor(3 - k), ids)
    s = acc.summary()
    assert [c.dense for c in s.calls] == [True, False, False]
    assert s.sparsity_of(s.calls[1]) == pytest.approx(2 / 3)
    first_call_r = acc.cache.rollout[1][0]
    assert first_call_r is not None
    acc.new_rollout()
    assert acc.cache.rollout == []
    with torch.no_grad():
        model(torch.randn(1, 4, 8), torch.tensor(3), ids)
    assert acc.summary().calls[-1].dense


def test_fused_rollout_step_sum_is_kept_per_step_until_its_row_changes():
    """A whole step reused along the rollout direction adds the row's sum over branches; the sum is
    computed once per (step, row version) and recomputed after a write to that row."""
    from tts.cache import ReuseCache

    cache = ReuseCache([0, 1, 0, 1], 2, ("rollout",))
    rows = [[torch.randn(2, 3) for _ in range(4)] for _ in range(2)]
    for k in range(2):
        for b in range(4):
            cache.write(b, k, rows[k][b])
    codes = [ROLLOUT] * 4
    first = cache.step_total(codes, 1)
    torch.testing.assert_close(first, sum(rows[1]))
    assert cache.step_total(codes, 1) is first  # kept: the row did not change
    cache.write(2, 1, torch.zeros(2, 3))
    again = cache.step_total(codes, 1)
    torch.testing.assert_close(again, rows[1][0] + rows[1][1] + rows[1][3])
    cache.write_rows(0, 1, torch.tensor([1]), torch.ones(1, 3), 0)
    torch.testing.assert_close(cache.step_total(codes, 1)[1], torch.ones(3) + rows[1][1][1] + rows[1][3][1])
    torch.testing.assert_close(cache.step_total(codes, 0), sum(rows[0]))
    cache.new_episode()
    with pytest.raises(RuntimeError, match="empty cache"):
        cache.step_total(codes, 0)


def test_enabling_rollout_changes_only_the_first_call_when_the_plan_never_picks_it():
    """The robot table's omni row vs its timestep-only row: with decisions that never choose rollout,
    turning the rollout direction on only makes each episode's first call dense; every later call is
    bit-identical to the same plan without that direction."""
    plan = tts.plans.from_tensor(torch.tensor(
        [[COMPUTE] * 6] + [[TIMESTEP, COMPUTE, TIMESTEP, TIMESTEP, COMPUTE, TIMESTEP]] * 3))
    torch.manual_seed(1)
    xs = [torch.randn(1, 4, 8) for _ in range(3 * 4)]
    outs, dense = {}, {}
    for dirs in (("timestep",), ("timestep", "rollout")):
        model, log, spec = make()
        with tts.accelerate(model, dirs, plan=plan, blocks={"blocks.*": spec}) as acc, torch.no_grad():
            outs[dirs] = [model(xs[4 * c + k], torch.tensor(4 - k), torch.arange(1)) for c in range(3) for k in range(4)]
            dense[dirs] = [c.dense for c in acc.summary().calls]
    assert dense == {("timestep",): [False] * 3, ("timestep", "rollout"): [True, False, False]}
    t_only, omni = outs[("timestep",)], outs[("timestep", "rollout")]
    assert not all(torch.equal(a, b) for a, b in zip(t_only[:4], omni[:4]))  # dense first call
    assert all(torch.equal(a, b) for a, b in zip(t_only[4:], omni[4:]))


def test_missing_rollout_entries_fall_back_to_compute():
    """A call longer than the previous one has no rollout entries for its extra steps."""
    model, log, spec = make()
    plan = tts.plans.from_tensor(torch.tensor([[COMPUTE] * 6] + [[ROLLOUT] * 6] * 5))
    acc = tts.accelerate(model, ("rollout",), plan=plan, blocks={"blocks.*": spec})
    ids = torch.arange(1)
    with torch.no_grad():
        for steps in (2, 4):
            for k in range(steps):
                model(torch.randn(1, 4, 8), torch.tensor(10 - k), ids)
    last = acc.summary().calls[-1]
    assert last.fallbacks == 2 * 6
    assert acc.summary().sparsity_of(last) == pytest.approx(1 / 4)


def test_mixed_batch_equals_each_sample_alone():
    model, log, spec = make()
    steps, nb, batch = 6, 6, 4
    rng = random.Random(7)
    dec = torch.tensor([[[rng.choice([0, 1, 2]) for _ in range(nb)] for _ in range(steps)] for _ in range(batch)],
                       dtype=torch.int8)  # [B, K, nb]
    x0 = torch.randn(batch, 4, 8, generator=torch.Generator().manual_seed(3))

    def sample(acc_model, x, ids):
        with torch.no_grad():
            for k in range(steps):
                x = acc_model(x, torch.tensor(steps - k), ids) * 0.5
        return x

    with tts.accelerate(model, ("forward", "timestep"), plan=tts.plans.from_tensor(dec), blocks={"blocks.*": spec}):
        log.computed.clear()
        together = sample(model, x0, torch.arange(batch))
        rows_run = sum(len(r) for _, _, r, _ in log.computed)
    assert rows_run == int((dec[:, 1:] == COMPUTE).sum()) + batch * nb  # step 0 always computes
    for s in range(batch):
        with tts.accelerate(model, ("forward", "timestep"), plan=tts.plans.from_tensor(dec[s]), blocks={"blocks.*": spec}):
            alone = sample(model, x0[s:s + 1], torch.arange(1))
        # equal up to GEMM round-off (a batched matmul may pick another kernel than a 1-row one)
        torch.testing.assert_close(together[s:s + 1], alone, rtol=1e-5, atol=1e-5)


def test_new_call_detected_from_timestep_and_explicitly():
    model, log, spec = make()
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2), blocks={"blocks.*": spec})
    ids = torch.arange(1)
    x = torch.randn(1, 4, 8)
    with torch.no_grad():
        for steps, start in ((5, 50), (3, 50), (4, 30), (2, 45), (1, 50), (1, 50)):
            for k in range(steps):  # decreasing timesteps; a call may start lower (img2img)
                model(x, torch.tensor(float(start - 10 * k)), ids)
    assert [len(c.steps) for c in acc.summary().calls] == [5, 3, 4, 2, 1, 1]
    acc.remove()
    acc = tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(2), blocks={"blocks.*": spec})
    with torch.no_grad():  # increasing timesteps (flow-matching style)
        for _ in range(2):
            for k in range(3):
                model(x, torch.tensor(0.1 * k), ids)
    assert [len(c.steps) for c in acc.summary().calls][-2:] == [3, 3]
    acc.new_call()
    assert acc.step_index == 0
    with torch.no_grad():
        for k in range(2):
            model(x, torch.tensor(0.0), ids)  # same timestep: only explicit boundaries split calls
            assert acc.step_index == k + 1
    assert len(acc.summary().calls[-1].steps) == 2
