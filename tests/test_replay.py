"""Prioritized replay (``algo.priority_alpha``): the sampler's draws and weights, and the SAC
update that weights its rows and sets their priorities."""

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from rlplat.agents.replay import PrioritySampler
from rlplat.agents.sac import PRIORITY_EPS, SACAgent, make_replay_buffer, net_spec
from rlplat.errors import DivergenceError


def filled_buffer(n: int, sampler) -> TensorDictReplayBuffer:
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(2 * n), sampler=sampler, batch_size=8)
    buffer.extend(TensorDict({"x": torch.arange(n, dtype=torch.float32)}, batch_size=[n]))
    return buffer


def test_draws_follow_the_priorities_and_weights_undo_them():
    sampler = PrioritySampler(capacity=8, alpha=0.5, beta=1.0, eps=1e-6)
    buffer = filled_buffer(4, sampler)
    errors = torch.tensor([0.0, 1.0, 4.0, 9.0])
    sampler.update_priority(torch.arange(4), errors)
    p = (errors + 1e-6) ** 0.5
    expected = p / p.sum()  # about 0, 1/6, 2/6, 3/6
    torch.manual_seed(0)
    index, info = sampler.sample(buffer.storage, 60_000)
    counts = torch.bincount(index, minlength=4).double() / 60_000
    sigma = (expected * (1 - expected) / 60_000).sqrt()
    assert torch.all((counts - expected).abs() <= 4 * sigma + 1e-9), counts
    # beta = 1: (N P(i))^-1, so a row's weight times its chance is the same for every row.
    weight = info["priority_weight"]
    assert torch.allclose(weight * expected[index] * 4, torch.ones_like(weight))
    # The seed fixes the draws.
    torch.manual_seed(0)
    assert torch.equal(sampler.sample(buffer.storage, 60_000)[0], index)


def test_draws_span_blocks_skip_unwritten_rows_and_follow_a_wrapped_storage():
    # 300 rows of a 330-row storage: 6 blocks of 64, the last one partly written; one block of
    # near-zero priorities.
    sampler = PrioritySampler(capacity=330, alpha=1.0, beta=0.5, eps=1e-9)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(330), sampler=sampler, batch_size=8)
    buffer.extend(TensorDict({"x": torch.zeros(300)}, batch_size=[300]))
    errors = torch.rand(300, generator=torch.Generator().manual_seed(1)) + 0.5
    errors[64:128] = 1e-6
    sampler.update_priority(torch.arange(300), errors)
    assert torch.allclose(sampler.block_sum, sampler.priority.view(-1, 64).sum(1))

    def check(n, draws=400_000):
        expected = sampler.priority[:n] / sampler.priority[:n].sum()
        torch.manual_seed(2)
        index, info = sampler.sample(buffer.storage, draws)
        assert int(index.max()) < n and int(index.min()) >= 0
        # The near-zero block holds ~3e-7 of the mass: 0.1 draws expected, a few at most.
        assert int(((index >= 64) & (index < 128)).sum()) <= 3
        counts = torch.bincount(index, minlength=n).double() / draws
        sigma = (expected * (1 - expected) / draws).sqrt()
        seen = expected * draws >= 5  # where a count is near normal
        assert torch.all((counts - expected).abs()[seen] <= 5 * sigma[seen])
        weight = info["priority_weight"]
        assert torch.allclose(weight, (n * expected[index]) ** -0.5)

    check(300)
    # 60 more rows wrap round: rows 300-329 and then 0-29 are new, at the largest priority.
    buffer.extend(TensorDict({"x": torch.ones(60)}, batch_size=[60]))
    assert len(buffer) == 330
    top = sampler.max_priority
    assert top == pytest.approx(float(errors.max()), rel=1e-6)  # alpha 1: the largest |error|
    assert torch.allclose(sampler.priority[:30], torch.full((30,), top, dtype=torch.float64))
    assert torch.allclose(sampler.priority[300:330], torch.full((30,), top, dtype=torch.float64))
    assert torch.allclose(sampler.block_sum, sampler.priority.view(-1, 64).sum(1))
    check(330)


def test_new_transitions_start_at_the_largest_priority_given():
    sampler = PrioritySampler(capacity=16, alpha=1.0, beta=0.4, eps=0.01)
    buffer = filled_buffer(4, sampler)
    assert sampler.priority[:4].tolist() == [1.0] * 4  # before any update
    sampler.update_priority(torch.tensor([0, 1]), torch.tensor([-3.0, 0.5]))  # |TD error|
    assert sampler.priority[:2].tolist() == pytest.approx([3.01, 0.51])
    buffer.extend(TensorDict({"x": torch.zeros(2)}, batch_size=[2]))
    assert sampler.priority[4:6].tolist() == pytest.approx([3.01, 3.01])
    assert sampler.priority[6:].sum() == 0  # never written: never drawn
    index, _ = sampler.sample(buffer.storage, 1000)
    assert int(index.max()) <= 5


def test_a_non_finite_td_error_is_refused_and_changes_no_priority():
    sampler = PrioritySampler(capacity=8, alpha=0.6, beta=0.4, eps=0.01)
    filled_buffer(4, sampler)
    before = sampler.priority.clone()
    for bad in (float("nan"), float("inf")):
        with pytest.raises(DivergenceError, match="1 of the 2 TD errors .* not finite"):
            sampler.update_priority(torch.tensor([0, 1]), torch.tensor([0.5, bad]))
    assert torch.equal(sampler.priority, before)


@pytest.mark.parametrize("bad", [dict(alpha=-0.1), dict(beta=-1.0), dict(eps=0.0)])
def test_the_sampler_refuses_bad_parameters(bad):
    with pytest.raises(ValueError, match="PrioritySampler"):
        PrioritySampler(capacity=4, **{"alpha": 0.5, "beta": 0.4, "eps": 0.01, **bad})


def test_the_config_picks_the_sampler():
    algo = OmegaConf.create({"buffer_size": 100, "batch_size": 8, "priority_beta": 0.4})
    uniform = make_replay_buffer({**algo, "priority_alpha": 0.0})
    assert type(uniform.sampler) is RandomSampler
    prioritized = make_replay_buffer({**algo, "priority_alpha": 0.6})
    assert isinstance(prioritized.sampler, PrioritySampler)
    assert (prioritized.sampler.alpha, prioritized.sampler.beta) == (0.6, 0.4)
    assert prioritized.sampler.eps == PRIORITY_EPS


@pytest.mark.slow
def test_a_prioritized_update_weights_its_rows_and_sets_their_priorities(scenarios):
    """Eager and compiled updates from a prioritized buffer draw the same rows, agree on the
    losses, and leave the same priorities: the drawn rows' from their TD errors, the others at
    the start value."""
    import torch._inductor.config

    from rlplat.experiment.config import compose_config
    from rlplat.experiment.factory import build_env
    from rlplat.experiment.training import replay

    cfg = compose_config(
        "train",
        [f"scenarios_dir={scenarios.path}", "drone=attacker_v4", "algo.priority_alpha=0.6"],
    )
    env = build_env(cfg, scenarios=scenarios, split="train", num_envs=16)
    torch.manual_seed(0)
    td, steps = env.reset(), []
    for _ in range(8):
        out, td = env.step_and_maybe_reset(td.set("action", env.action_spec.rand()))
        steps.append(out)
    transitions = replay(torch.stack(steps, dim=1), env.group, cfg.algo)
    algo = {**OmegaConf.to_container(cfg.algo), "buffer_size": 1000, "batch_size": 32}

    def agent_and_buffer(compile_):
        torch.manual_seed(0)
        agent = SACAgent(
            net_spec(env.obs_fn.scale, 3, cfg.algo), env.action_spec[0], gamma=0.99, tau=0.02,
            actor_lr=1e-3, critic_lr=1e-3, alpha_lr=1e-3, compile=compile_,
        )  # fmt: skip
        buffer = make_replay_buffer(algo)
        buffer.extend(transitions)
        return agent, buffer

    with torch._inductor.config.patch(fallback_random=True):
        eager, eager_buffer = agent_and_buffer(False)
        compiled, compiled_buffer = agent_and_buffer(True)
        drawn = torch.zeros(len(transitions), dtype=torch.bool)
        for step in range(SACAgent.WARMUP_CALLS + 2):
            torch.manual_seed(step)  # the rows the update will draw
            index, _ = eager_buffer.sampler.sample(eager_buffer.storage, 32)
            drawn[index] = True
            torch.manual_seed(step)
            expected = eager.update_from(eager_buffer)
            torch.manual_seed(step)
            got = compiled.update_from(compiled_buffer)
            assert got.keys() == expected.keys() and "td_error" not in got
            for name in expected:
                assert got[name].item() == pytest.approx(expected[name].item(), rel=1e-3), name
        # The weights reach the losses: all ones is the unweighted update (TorchRL's weighted
        # mean), other weights another one.
        batch = transitions[:32]
        losses = []
        for weights in (None, torch.ones(32), torch.linspace(0.1, 2.0, 32)):
            agent, _ = agent_and_buffer(False)
            torch.manual_seed(0)
            losses.append(agent.update(batch.clone(), weights)["loss_qvalue"].item())
        assert losses[1] == pytest.approx(losses[0], rel=1e-6)
        assert losses[2] != pytest.approx(losses[0], rel=1e-3)
    eager_p, compiled_p = eager_buffer.sampler.priority, compiled_buffer.sampler.priority
    n = len(transitions)
    assert torch.allclose(eager_p[:n], compiled_p[:n], rtol=1e-3)
    # Drawn rows carry their TD error's priority, the others the start value (1).
    assert torch.all(eager_p[:n][~drawn] == 1.0)
    assert torch.all(eager_p[:n][drawn] != 1.0)
    assert torch.all(eager_p[:n][drawn] >= PRIORITY_EPS**0.6 - 1e-12)


def test_a_run_with_prioritized_replay_updates_through_it(
    scenarios, tmp_path, tiny_run, monkeypatch
):
    """``algo.priority_alpha`` > 0: the training loop's every update draws from the prioritized
    sampler and gives it the drawn rows' TD errors."""
    calls = []
    update = PrioritySampler.update_priority

    def counted(self, index, priority, **kw):
        calls.append((len(index), bool(torch.isfinite(torch.as_tensor(priority)).all())))
        return update(self, index, priority, **kw)

    monkeypatch.setattr(PrioritySampler, "update_priority", counted)
    summary = tiny_run(scenarios, tmp_path / "run", "algo.priority_alpha=0.6")
    assert calls and len(calls) == summary["updates"]
    assert all(n == 32 and finite for n, finite in calls)  # algo.batch_size rows, finite errors
