"""Scripted policies: TensorDictModules that read only the env's output keys."""

import pytest
import torch

from rlplat import make_env
from rlplat.agents.policies import (
    POLICIES,
    ProportionalNavigation,
    PurePursuit,
    SetpointFollower,
    make_scripted_policy,
)

DRONE = {"attacker": "drone=attacker_v3", "defender": "drone=defender_v1"}


@pytest.mark.parametrize("name", sorted(POLICIES))
def test_reads_only_its_keys_of_the_env_output(scenarios, name):
    role = POLICIES[name].role
    env = make_env(DRONE[role], scenarios=scenarios, num_envs=6)
    policy = make_scripted_policy(name, env)
    td = env.reset()
    for _ in range(5):  # move away from the start so that velocities are not all zero
        td = env.step(policy(td))["next"]
    keys = list(policy.in_keys)
    assert set(keys) <= set(env.observation_spec.keys())
    alone = policy(td.select(*keys))[env.action_key]  # nothing but its keys
    full = policy(td.clone())[env.action_key]
    torch.testing.assert_close(alone, full, rtol=0, atol=0)
    assert env.full_action_spec[env.action_key].is_in(alone)
    assert alone.abs().amax() > 0  # it flies


def test_pure_pursuit_is_gain_times_separation_saturated():
    policy = PurePursuit(gain=1.0, learner="attacker", attackers=1, defenders=1, team=False)
    positions = torch.tensor([[[0.0, 0.0, 10.0], [10.0, -0.5, 10.2]]])  # attacker, defender
    max_speed = torch.tensor([[2.0, 1.0]])
    action = policy(positions, max_speed, torch.zeros(1, 1, dtype=torch.bool))
    # per axis: clamp(gain * d / v_max): x saturates, y and z do not
    torch.testing.assert_close(action, torch.tensor([[1.0, -0.25, 0.1]]))


def pn_action(velocity_other, rel, max_speed=5.0, **kwargs) -> list[float]:
    """Proportional navigation of a lone attacker at 10 m altitude, the defender at ``rel``."""
    module = ProportionalNavigation(
        gain=1.0, learner="attacker", attackers=1, defenders=1, team=False, **kwargs
    )
    positions = torch.tensor([[[0.0, 0.0, 10.0], [rel[0], rel[1], 10.0 + rel[2]]]])
    velocities = torch.zeros(1, 2, 3)
    velocities[0, 1] = torch.tensor(velocity_other)
    speeds = torch.tensor([[max_speed, 2.0]])
    return module(positions, velocities, speeds, torch.zeros(1, 1, dtype=torch.bool))[0].tolist()


def test_proportional_navigation_leads_a_moving_target():
    # Closing 10 m at 5 m/s takes 2 s; the target moves 2 m/s along y: aim 0.5 * 4 m ahead.
    assert pn_action([0.0, 2.0, 0.0], (10.0, 0.0, 0.0)) == pytest.approx([1.0, 0.4, 0.0])
    assert pn_action([0.0, 2.0, 0.0], (10.0, 0.0, 0.0), lead=0.0) == pytest.approx([1, 0, 0])
    # A target faster than the learner on an axis: the lead time is capped.
    aim = -1.0 + 0.5 * -6.0 * 1.0
    capped = pn_action([-6.0, 0.0, 0.0], (-1.0, 0.0, 0.0), max_lead_time=1.0)
    assert capped[0] == pytest.approx(aim / 5.0)


def test_setpoint_follower_holds_once_the_route_is_flown():
    policy = SetpointFollower(gain=1.0, learner="defender", attackers=1, defenders=1, team=False)
    positions = torch.tensor([[[50.0, 0.0, 10.0], [0.0, 0.0, 10.0]]])
    max_speed = torch.tensor([[3.0, 2.0]])
    setpoints = torch.tensor([[[1.0, -4.0, 10.0]]])
    flying = policy(positions, max_speed, setpoints, torch.tensor([[False]]))
    torch.testing.assert_close(flying, torch.tensor([[0.5, -1.0, 0.0]]))
    done = policy(positions, max_speed, setpoints, torch.tensor([[True]]))
    torch.testing.assert_close(done, torch.zeros(1, 3))


def test_a_team_flies_one_action_per_drone(tmp_path, write_small_set):
    two = write_small_set(tmp_path / "2v1", "scenario.attackers=2")
    env = make_env("drone=attacker_v4", scenarios=two, num_envs=3)  # a 3-d action per drone
    policy = make_scripted_policy("proportional_navigation", env)
    td = policy(env.reset())
    assert env.action_key == ("attacker", "action")
    assert td[env.action_key].shape == (3, 2, 3)
