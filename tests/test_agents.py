import pytest
import torch
from tensordict import TensorDict

from rlplat.agents.transitions import n_step_transitions, shape_rewards
from rlplat.eval.baselines import PurePursuitPolicy
from rlplat.eval.episodes import evaluate
from tests.test_env import scenarios  # noqa: F401  (module-scoped fixture)


def trajectory(done_at=(2,), T=6):
    """One env, T steps: reward t+1, observation t, next observation t+1."""
    obs = torch.arange(T, dtype=torch.float32).view(1, T, 1)
    done = torch.zeros(1, T, 1, dtype=torch.bool)
    for t in done_at:
        done[0, t] = True
    nxt = {"observation": obs + 1, "reward": obs + 1, "done": done, "terminated": done.clone()}
    return TensorDict({"observation": obs, "action": obs, "next": nxt}, batch_size=[1, T])


def test_n_step_sums_discounted_rewards_within_the_episode_and_the_batch():
    out = n_step_transitions(trajectory(), n=3, gamma=0.5)
    # Episode 1 ends at t=2; episode 2 is cut by the batch end at t=5.
    assert out["next", "reward"].flatten().tolist() == [2.75, 3.5, 3.0, 8.0, 8.0, 6.0]
    assert out["steps_to_next_obs"].flatten().tolist() == [3, 2, 1, 3, 2, 1]
    assert out["next", "observation"].flatten().tolist() == [3, 3, 3, 6, 6, 6]
    # A window that reaches a terminal step is terminal: no bootstrap past a capture or crash.
    assert out["next", "terminated"].flatten().tolist() == [True] * 3 + [False] * 3
    assert torch.equal(out["observation"], trajectory()["observation"])  # s_t, a_t unchanged


def test_potential_shaping_rewards_progress_and_telescopes():
    batch = trajectory(done_at=())
    batch["distance"] = torch.tensor([[10.0, 8.0, 6.0, 5.0, 5.0, 7.0]]).unsqueeze(-1)
    batch["next", "distance"] = batch["distance"].roll(-1, 1)
    out = shape_rewards(batch, "distance", weight=-1.0, gamma=1.0)
    bonus = (out["next", "reward"] - batch["next", "reward"]).flatten()
    assert bonus[:4].tolist() == [2.0, 2.0, 1.0, 0.0]  # metres gained on the opponent
    assert bonus[4].item() == -2.0  # losing ground costs as much
    # With gamma = 1 the bonuses of a path sum to Phi(end) - Phi(start): no policy is favoured
    # for where it ends up, only for getting there.
    assert bonus[:5].sum().item() == pytest.approx(-1.0 * (7.0 - 10.0))
    assert torch.equal(batch["next", "reward"], trajectory(done_at=())["next", "reward"])
    assert shape_rewards(batch, "distance", weight=0.0, gamma=0.99) is batch


def test_one_step_is_the_identity():
    batch = trajectory()
    assert n_step_transitions(batch, n=1, gamma=0.99) is batch


def test_pure_pursuit_reference_captures_and_a_hover_does_not(scenarios):  # noqa: F811
    from rlplat.config import compose_config
    from rlplat.envs.factory import build_env

    cfg = compose_config("train", [f"scenarios_dir={scenarios.path}"])
    env = build_env(
        cfg, scenarios=scenarios, split="val", num_envs=len(scenarios.split("val")),
        scenario_order="sequential",
    )  # fmt: skip
    pursuit = evaluate(env, PurePursuitPolicy(env))
    hover = evaluate(env, lambda td: td.set("action", torch.zeros(env.action_spec.shape)))
    assert pursuit.capture_rate > 0.5
    assert hover.capture_rate < pursuit.capture_rate
    assert not pursuit.grounded.any()
    assert pursuit.capture_rate == pytest.approx(evaluate(env, PurePursuitPolicy(env)).capture_rate)
