"""The route-intercept law: the defender's known route as a prediction, the law that flies to
where it can be met, a learned correction to that law and the observation of its meeting
point."""

import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from rlplat import make_env
from rlplat.agents.policies import make_scripted_policy
from rlplat.envs.kinematics import (
    SetpointFlight,
    follow_route,
    route_intercept,
    route_path,
    route_times,
    setpoint_flight,
)
from rlplat.errors import ConfigError
from rlplat.eval.episodes import evaluate

PLAIN = "drone=attacker_v3"  # the plain velocity action
V10 = "drone=attacker_v10"  # pursuit_intercept and route_law
V11 = "drone=attacker_v11"  # attacker_v10 with pursuit_conform
ROUTE_ONLY = "scenario.strategy_mix={setpoints: 1, nn: 0}"


def test_route_path_flies_each_axis_at_full_speed_then_moves_on():
    route = torch.tensor([[[8.0, 0.0, 0.0], [8.0, 6.0, 3.0], [16.0, 6.0, 3.0]]])
    times = torch.tensor([0.0, 1.0, 4.0, 5.0, 6.0, 10.0, 100.0])
    path = route_path(torch.zeros(1, 3), route, torch.tensor([2.0]), times)[0]
    expected = [[0, 0, 0], [2, 0, 0], [8, 0, 0], [8, 2, 2], [8, 4, 3], [14, 6, 3], [16, 6, 3]]
    torch.testing.assert_close(path, torch.tensor(expected, dtype=torch.float32))


def test_the_meeting_point_is_the_earliest_point_of_the_path_reached_in_time():
    g = torch.Generator().manual_seed(0)
    n, times = 256, torch.arange(1, 41) * 0.25  # 10 s: some paths stay out of reach
    own = torch.rand(n, 3, generator=g) * 80 - 40
    other = torch.rand(n, 3, generator=g) * 20
    route = torch.rand(n, 6, 3, generator=g) * 60 - 30
    own_speed, other_speed = torch.rand(n, generator=g) * 4 + 1, torch.rand(n, generator=g) * 4 + 1
    point, due, found = route_intercept(
        own, own_speed, other, route, other_speed, times=times, lag=0.5, reach=1.2
    )
    path = route_path(other, route, other_speed, times)  # (n, T, 3)
    gap = (path - own.unsqueeze(1)).abs().amax(-1)
    ok = gap <= own_speed.unsqueeze(1) * (times - 0.5).clamp_min(0) + 1.2
    assert 0 < int(found.sum()) < n  # both cases occur
    first = ok.float().argmax(1)
    torch.testing.assert_close(due[found], times[first[found]])
    torch.testing.assert_close(point[found], path[found, first[found]])
    # Where none is reachable: the path's last point, at the last time.
    torch.testing.assert_close(point[~found], path[~found, -1])
    assert (due[~found] == times[-1]).all()
    # A time limit hides what comes after it.
    left = torch.full((n,), 5.0)
    _, due_left, found_left = route_intercept(
        own, own_speed, other, route, other_speed, times=times, lag=0.5, reach=1.2,
        time_left=left,
    )  # fmt: skip
    assert torch.equal(found_left, found & (due <= 5.0))
    assert (due_left <= 5.0).all()
    # Arguments broadcast to the batch: one speed and one time limit for every pursuit.
    one = route_intercept(
        own, own_speed[:1].expand(n).contiguous(), other, route, other_speed, times=times,
        lag=0.5, reach=1.2, time_left=left,
    )  # fmt: skip
    shared = route_intercept(
        own, own_speed[0], other, route, other_speed, times=times, lag=0.5, reach=1.2,
        time_left=torch.tensor(5.0),
    )  # fmt: skip
    assert all(torch.equal(a, b) for a, b in zip(one, shared, strict=True))


def test_a_longer_look_ahead_meets_a_slow_attacker_further_along_the_route():
    # The law's horizon only adds instants: a point found within 60 s is the same point, and
    # an attacker too slow to meet the defender within 60 s may meet it further along.
    g = torch.Generator().manual_seed(3)
    n = 512
    own, other = torch.rand(n, 3, generator=g) * 160 - 80, torch.rand(n, 3, generator=g) * 20
    route = torch.rand(n, 6, 3, generator=g) * 160 - 80
    own_speed = torch.rand(n, generator=g) * 2 + 0.5
    other_speed = torch.rand(n, generator=g) * 4 + 1
    args = (own, own_speed, other, route, other_speed)
    near = route_intercept(*args, times=route_times(60.0), lag=0.5, reach=1.2)
    far = route_intercept(*args, times=route_times(120.0), lag=0.5, reach=1.2)
    assert (far[2] | ~near[2]).all()
    assert torch.equal(far[0][near[2]], near[0][near[2]])
    assert torch.equal(far[1][near[2]], near[1][near[2]])
    later = far[2] & ~near[2]
    assert later.sum() >= 10 and (far[1][later] > 60.0).all()


def test_a_setpoints_defender_is_never_ahead_of_its_route_path(tmp_path, write_small_set):
    # The path has no velocity lag and no slowing down near a setpoint: a defender of the
    # ``setpoints`` strategy reaches each setpoint no earlier than the path does, give or take
    # the acceptance radius it moves on within.
    scenarios = write_small_set(tmp_path, ROUTE_ONLY)
    env = make_env(PLAIN, scenarios=scenarios, num_envs=32, split="val")
    td = env.reset()
    k = env.num_attackers
    start, speed = td["positions"][:, k], td["max_speed"][:, k]
    route = env.routes[env.route[:, 0]]  # (N, S, 3), every defender at its first setpoint
    times = torch.arange(1, 301) * env.control_period
    path = route_path(start, route, speed, times)  # (N, T, 3)
    # When the path is within the acceptance radius of each setpoint for the first time.
    near = (path.unsqueeze(2) - route.unsqueeze(1)).norm(dim=-1) <= env.setpoint_acceptance
    first = torch.where(near.any(1), near.float().argmax(1), len(times))  # (N, S) steps
    reached = torch.full_like(first, len(times))
    hold = torch.zeros(32, 3)
    for step in range(1, 301):
        before = td["waypoint"][:, 0]
        td = env.step(td.set("action", hold))["next"]
        moved = td["waypoint"][:, 0] > before
        reached[moved, before[moved]] = step
        if td["done"].all():
            break
    seen = reached < len(times)
    assert seen.sum() >= 32  # many setpoints were reached
    assert (reached[seen] >= first[seen] - 1).all()  # one step of rounding


def test_a_leg_ends_with_the_proportional_approach_and_starts_after_the_lag():
    flight = SetpointFlight(lag=0.5, gain=1.0, acceptance=1.0)
    # 10 m: full speed 4 m/s until 4 m out (1.5 s), then exp(-t) from 4 m to 1 m (ln 4 s),
    # against 2.5 s at full speed. 2 m: exp(-t) from the start. 0.5 m: within acceptance.
    extra = flight.approach(torch.tensor([10.0, 2.0, 0.5]), torch.tensor(4.0))
    torch.testing.assert_close(extra, torch.tensor([math.log(4) - 1.0, math.log(2) - 0.5, 0.0]))
    route = torch.tensor([[[10.0, 0.0, 0.0], [10.0, 0.0, 0.0]]])  # the last setpoint repeated
    times = torch.tensor([0.5, 1.5, 2.5, 3.0, 100.0])
    path = route_path(torch.zeros(1, 3), route, torch.tensor([4.0]), times, flight=flight)[0]
    torch.testing.assert_close(path[:, 0], torch.tensor([0.0, 4.0, 8.0, 10.0, 10.0]))
    # Already flying the leg at full speed: no lag left.
    moving = route_path(torch.zeros(1, 3), route, torch.tensor([4.0]), times,
                        velocity=torch.tensor([[4.0, 0.0, 0.0]]), flight=flight)[0]  # fmt: skip
    torch.testing.assert_close(moving[:2, 0], torch.tensor([2.0, 6.0]))
    with pytest.raises(ValueError, match="SetpointFlight.acceptance"):
        SetpointFlight(lag=0.9, gain=1.0, acceptance=0.0)


def test_the_lagged_path_predicts_a_setpoints_defender(tmp_path, write_small_set):
    # With the env's setpoint gain and acceptance and the velocity lag the law assumes, the path
    # stays within a few metres of a route-flying defender for 20 s; without lags it runs ahead
    # (medians here 1.7, 1.6, 2.3 m at 5, 10, 20 s against 5, 9, 13 m).
    scenarios = write_small_set(tmp_path, ROUTE_ONLY)
    env = make_env(PLAIN, scenarios=scenarios, num_envs=32, split="val")
    td = env.reset()
    k, steps = env.num_attackers, 200
    p0, v0, speed = td["positions"][:, k], td["velocities"][:, k], td["max_speed"][:, k]
    route = env.routes[env.route[:, 0]]  # (N, S, 3), every defender at its first setpoint
    hold = torch.zeros(env.action_spec.shape)
    flown, free = [], torch.ones(32, dtype=torch.bool)
    for _ in range(steps):
        td = env.step(td.set("action", hold))["next"]
        flown.append(td["positions"][:, k])
        free &= ~td["done"].reshape(-1)  # neither caught nor truncated: still flying its route
    assert free.sum() >= 16
    times = torch.tensor([5.0, 10.0, 20.0])
    at = [round(float(t) / env.control_period) - 1 for t in times]
    actual = torch.stack(flown, 1)[:, at]  # (N, 3, 3)
    flight = setpoint_flight(env.setpoint_gain, env.setpoint_acceptance)
    lagged = route_path(p0, route, speed, times, velocity=v0, flight=flight)
    plain = route_path(p0, route, speed, times)
    error = (lagged - actual).norm(dim=-1)[free]
    assert (error.median(0).values < 3.0).all()
    assert error.median() * 3 < (plain - actual).norm(dim=-1)[free].median()


# attacker_v12's law: a later homing, and a start-up lag the meeting point allows for.
V12_LAW = {"homing_time": 0.5, "start_lag": 0.5}


def test_the_search_in_blocks_gives_the_full_searchs_answer(device):
    # Later blocks of instants are searched only by the pursuers without a point yet; the
    # answer must be the full search's (the path at every instant, the first one reachable
    # gathered from it), value for value, wherever the point lies. On a CUDA device the
    # search is one full search (kinematics.blocked_search): its answer is checked alike.
    from rlplat.envs import kinematics

    g = torch.Generator().manual_seed(2)
    n, times = 2048, route_times(60.0, device)  # 240 instants: the env's

    def draw(*shape):
        return torch.rand(*shape, generator=g).to(device)

    other = draw(n, 2, 3) * 40  # a batch of two dimensions
    own = other + (draw(n, 2, 3) * 2 - 1).pow(3) * 60  # some near, some far
    route = other.unsqueeze(-2) + draw(n, 2, 6, 3) * 120 - 60
    own_speed = draw(n, 2) * 4 + 0.5
    other_speed = draw(n, 2) * 4 + 0.5
    velocity = torch.randn(n, 2, 3, generator=g).to(device)
    flight = setpoint_flight(1.0, 0.5)
    path = route_path(other, route, other_speed, times, velocity=velocity, flight=flight)
    gap = (path - own.unsqueeze(-2)).abs().amax(-1)  # (n, 2, T)
    reachable = gap <= own_speed.unsqueeze(-1) * (times - 0.5).clamp_min(0) + 1.2
    for left in (None, draw(n, 2) * 70):
        point, due, found = route_intercept(
            own, own_speed, other, route, other_speed, times=times, lag=0.5, reach=1.2,
            time_left=left, other_velocity=velocity, flight=flight,
        )  # fmt: skip
        assert point.device == own.device
        ok, last = reachable, torch.full(found.shape, len(times) - 1, device=device)
        if left is not None:
            within = times <= left.unsqueeze(-1)
            ok, last = ok & within, (within.sum(-1) - 1).clamp_min(0)
        first = torch.where(ok.any(-1), ok.to(torch.uint8).argmax(-1), last)
        assert torch.equal(found, ok.any(-1)) and torch.equal(due, times[first])
        expected = path.gather(-2, first[..., None, None].expand(n, 2, 1, 3)).squeeze(-2)
        assert torch.equal(point, expected)
        # Every block answers some: points in the first, the second and the last, and none.
        edges = (0, *kinematics.SEARCH_BLOCKS, len(times))
        for lo, hi in zip(edges, edges[1:], strict=False):
            assert (found & (first >= lo) & (first < hi)).sum() >= 10, (lo, hi)
        assert (~found).sum() >= 10


def test_any_blocks_give_the_same_answer(monkeypatch):
    # The blocks are where the search pauses, in any order, repeated or out of range.
    from rlplat.envs import kinematics

    g = torch.Generator().manual_seed(5)
    own, other = torch.rand(512, 3, generator=g) * 80, torch.rand(512, 3, generator=g) * 80
    route = other.unsqueeze(-2) + torch.rand(512, 4, 3, generator=g) * 100 - 50
    speeds = torch.rand(2, 512, generator=g) * 4 + 0.5
    args = (own, speeds[0], other, route, speeds[1])
    kwargs = {"times": route_times(60.0), "lag": 0.5, "reach": 1.2}
    expected = route_intercept(*args, **kwargs)
    for blocks in [(), (32, 0, 8, 8), (500, -3, 239, 1)]:
        monkeypatch.setattr(kinematics, "SEARCH_BLOCKS", blocks)
        for got, want in zip(route_intercept(*args, **kwargs), expected, strict=True):
            assert torch.equal(got, want), blocks


def test_an_env_stepped_past_its_episode_end_keeps_its_meeting_point(scenarios):
    # An evaluation steps every env of a wave until the last episode ends: an env whose
    # episode has ended skips the search and keeps the point of the step it ended on; an env
    # whose episode ran into this step (the one it ends on included) gets the full search's.
    n = len(scenarios.split("val"))
    env = make_env(V11, "env.time_limit=4", "env.scenario_order=sequential", scenarios=scenarios,
                   num_envs=n, split="val")  # fmt: skip
    td = env.reset()
    law = make_scripted_policy("route_intercept", env)
    kept: dict[int, list[torch.Tensor]] = {}  # each ended env's point, as it ended
    some_ended = False
    for _ in range(50):
        before = env.ended.clone()
        td = env.step(law(td))["next"]
        p, v = env.dynamics.position, env.dynamics.velocity
        for now, searched in zip(env._meeting, env._meet(p, v, slice(None)), strict=True):
            assert torch.equal(now[~before], searched[~before])
        for i, point in kept.items():
            assert all(torch.equal(x[i], y) for x, y in zip(env._meeting, point, strict=True))
        assert torch.equal(env.ended, before | td["done"].squeeze(-1))
        for i in (env.ended & ~before).nonzero().squeeze(-1).tolist():
            kept[i] = [x[i].clone() for x in env._meeting]
        some_ended |= 0 < int(before.sum()) < n
    assert some_ended and env.ended.all()  # some episodes ended early, every one by 40 steps
    # A partial reset clears its envs' flags alone and searches them again.
    mask = torch.arange(n) % 2 == 0
    env.reset(td.set("_reset", mask.unsqueeze(-1)))
    assert torch.equal(env.ended, ~mask)
    p, v = env.dynamics.position, env.dynamics.velocity
    for now, searched in zip(env._meeting, env._meet(p, v, slice(None)), strict=True):
        assert torch.equal(now[mask], searched[mask])
    for i in (~mask).nonzero().squeeze(-1).tolist():
        assert all(torch.equal(x[i], y) for x, y in zip(env._meeting, kept[i], strict=True))


def test_an_evaluation_skips_no_meeting_point_it_counts(scenarios, monkeypatch):
    # The skip leaves every counted step as it was: the same episodes with every env searched.
    from rlplat.envs.pursuit import PursuitEnv

    n = len(scenarios.split("val"))
    env = make_env(V11, "env.scenario_order=sequential", scenarios=scenarios, num_envs=n,
                   split="val")  # fmt: skip
    law = make_scripted_policy("route_intercept", env)
    skipping = evaluate(env, law)
    meeting = PursuitEnv.meeting
    monkeypatch.setattr(PursuitEnv, "meeting", lambda self, p, v, running=None: meeting(self, p, v))
    searched = evaluate(env, law)
    assert skipping.length.float().std() > 0  # episodes of different lengths: envs ran past theirs
    keys = ("captured", "grounded", "returns", "length", "min_distance", "time_to_capture",
            "visible_fraction", "defender_route_fraction", "defender_caught")  # fmt: skip
    for key in keys:
        a, b = getattr(skipping, key), getattr(searched, key)
        assert torch.equal(a.nan_to_num(), b.nan_to_num()), key
    for key, value in skipping.term_sums.items():
        assert torch.equal(value, searched.term_sums[key]), key


def test_the_start_up_lag_moves_the_meeting_later():
    g = torch.Generator().manual_seed(1)
    n, times = 256, torch.arange(1, 81) * 0.25
    own, other = torch.rand(n, 3, generator=g) * 60 - 30, torch.rand(n, 3, generator=g) * 20
    route = torch.rand(n, 6, 3, generator=g) * 60 - 30
    own_speed, other_speed = torch.rand(n, generator=g) * 4 + 1, torch.rand(n, generator=g) * 4 + 1
    args = (own, own_speed, other, route, other_speed)
    _, due, found = route_intercept(*args, times=times, lag=0.0, reach=1.2)
    _, due_lag, found_lag = route_intercept(*args, times=times, lag=0.5, reach=1.2)
    assert (found | ~found_lag).all()  # reachable with a lag: reachable without
    both = found & found_lag
    assert (due_lag[both] >= due[both]).all() and (due_lag[both] > due[both]).any()


@pytest.mark.parametrize(
    "law",
    [{}, V12_LAW, {**V12_LAW, "horizon": 120.0}, {**V12_LAW, "unreachable": "head_off"}],
    ids=["default", "attacker_v12", "looking_120_s_ahead", "heading_off"],
)
def test_a_zero_correction_flies_the_route_intercept_law(scenarios, law):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    knobs = [f"action.{k}={v}" for k, v in law.items()]
    law_env = make_env(PLAIN, "action=route_law", *knobs, scenarios=scenarios, num_envs=n,
                       split="val")  # fmt: skip
    assert law_env.meeting_lag == law.get("start_lag", 0.0)
    assert law_env.meeting_horizon == law.get("horizon", 60.0)  # the time limit by default
    assert law_env.law_horizon == law.get("horizon")
    route = make_scripted_policy("route_intercept", plain, **law)
    a, b = plain.reset(), law_env.reset()
    running = torch.ones(n, dtype=torch.bool)  # past its episode's end, an env is not compared
    for _ in range(40):
        a = plain.step(route(a))["next"]
        b = law_env.step(b.set("action", torch.zeros(n, 3)))["next"]
        torch.testing.assert_close(a["positions"][running], b["positions"][running], rtol=0,
                                   atol=1e-5)  # fmt: skip
        running &= ~a["done"].squeeze(-1)
    assert running.sum() >= n // 2


@pytest.mark.parametrize(
    "law",
    [{}, V12_LAW, {**V12_LAW, "unreachable": "head_off"}],
    ids=["default", "attacker_v12", "heading_off"],
)
def test_a_scripted_policy_flies_its_own_commands_through_the_route_law(scenarios, law):
    # By name, route_intercept is the law the env's action corrects (its homing and lag).
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    knobs = [f"action.{k}={v}" for k, v in law.items()]
    law_env = make_env(PLAIN, "action=route_law", *knobs, scenarios=scenarios, num_envs=n,
                       split="val")  # fmt: skip
    for name in ("proportional_navigation", "route_intercept"):
        on_plain = make_scripted_policy(name, plain, **(law if name == "route_intercept" else {}))
        through = make_scripted_policy(name, law_env)
        a, b = plain.reset(), law_env.reset()
        running = torch.ones(n, dtype=torch.bool)  # compared until its episode ends
        for _ in range(30):
            a = plain.step(on_plain(a))["next"]
            b = through(b)
            if name == "route_intercept":  # the law itself: a zero correction
                assert b["action"][running].abs().max() < 1e-6
            b = law_env.step(b)["next"]
            torch.testing.assert_close(a["positions"][running], b["positions"][running], rtol=0,
                                       atol=1e-4)  # fmt: skip
            running &= ~a["done"].squeeze(-1)
        assert running.sum() >= n // 2


def slow_attackers(tmp_path, write_small_set, attacker_high, defender_low):
    """A set of slow attackers against fast route-flying defenders, and its val split's size."""
    scenarios = write_small_set(
        tmp_path, ROUTE_ONLY, f"scenario.params.attacker_max_speed.high={attacker_high}",
        f"scenario.params.defender_max_speed.low={defender_low}",
    )  # fmt: skip
    return scenarios, len(scenarios.split("val"))


def law_commands(env, td, aim, scenarios):
    """The first attacker's two commands in the reset state ``td``: flying to ``aim`` (the
    meeting point, (N, k, 3) m) and proportional navigation's."""
    own, speed = td["positions"][:, 0], td["max_speed"][:, :1]
    fly_to = (env.action_fn.gain * (aim[:, 0] - own) / speed).clamp(-1, 1)
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=td.shape[0], split="val")
    return fly_to, make_scripted_policy("proportional_navigation", plain)(td.clone())["action"]


def test_the_law_flies_to_the_meeting_point_until_homing(tmp_path, write_small_set):
    # The meeting points lie far ahead.
    scenarios, n = slow_attackers(tmp_path, write_small_set, 2, 3)
    env = make_env(V10, scenarios=scenarios, num_envs=n, split="val")
    td = env.reset()
    aim, due, found = env.meeting(env.dynamics.position, env.dynamics.velocity)
    away = found[:, 0] & (due[:, 0] > 2.0)  # the law flies to the point
    assert away.sum() >= 3
    guidance = env.guidance(env.dynamics.position, env.dynamics.velocity)[:, 0]
    expected, pn = law_commands(env, td, aim, scenarios)
    torch.testing.assert_close(guidance[away], expected[away])
    homing = ~away
    torch.testing.assert_close(guidance[homing], pn[homing])


def test_out_of_reach_the_law_chases_or_heads_the_defender_off(tmp_path, write_small_set):
    # Many meeting points are out of reach.
    scenarios, n = slow_attackers(tmp_path, write_small_set, 1.5, 3.5)
    chase, head_off = (
        make_env(V10, f"action.unreachable={u}", scenarios=scenarios, num_envs=n, split="val")
        for u in ("chase", "head_off")
    )
    assert (chase.action_fn.unreachable, head_off.action_fn.unreachable) == ("chase", "head_off")
    td = head_off.reset()
    chase.reset()
    p, v = head_off.dynamics.position, head_off.dynamics.velocity
    aim, due, found = head_off.meeting(p, v)
    out = ~found[:, 0]
    assert out.sum() >= 3 and found[:, 0].any()
    # Out of reach the answer is where the route puts the defender 60 s on (the search's end).
    assert (due[out, 0] == 60.0).all()
    fly_to, pn = law_commands(head_off, td, aim, scenarios)
    g_head, g_chase = (env.guidance(p, v)[:, 0] for env in (head_off, chase))
    torch.testing.assert_close(g_head[out], fly_to[out])
    torch.testing.assert_close(g_chase[out], pn[out])
    torch.testing.assert_close(g_head[~out], g_chase[~out])  # in reach: one law
    differ = (g_head[out] - g_chase[out]).abs().amax(-1) > 0.1  # saturated commands may agree
    assert differ.float().mean() >= 0.5
    assert head_off.action_fn.card()["guidance"]["unreachable"] == "head_off"
    assert any("holds" in line for line in head_off.action_fn.describe())


def test_the_route_law_refuses_an_unknown_way_out_of_reach(scenarios):
    with pytest.raises(ConfigError, match=r"^action.unreachable: unknown 'wait'; valid: chase, "):
        make_env(V10, "action.unreachable=wait", scenarios=scenarios, num_envs=2)
    with pytest.raises(ConfigError, match=r"^route_intercept.unreachable: unknown 'wait'"):
        make_scripted_policy("route_intercept", make_env(PLAIN, scenarios=scenarios),
                             unreachable="wait")  # fmt: skip


def test_the_route_law_meets_fast_route_flying_defenders_as_often_as_pn(tmp_path, write_small_set):
    # Where the route is known and the defender faster, flying ahead on it does at least as
    # well as chasing: a law that flew anywhere else would fall far below (0.545 against 0.440
    # here with the defender's lags in the path, 0.455 without).
    scenarios = write_small_set(
        tmp_path, ROUTE_ONLY, "scenario.n_test=200", "scenario.params.attacker_max_speed.high=3",
        "scenario.params.defender_max_speed.low=3",
    )  # fmt: skip
    n = len(scenarios.split("test"))
    env = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="test")
    rate = {
        name: evaluate(env, make_scripted_policy(name, env)).captured.float().mean().item()
        for name in ("proportional_navigation", "route_intercept")
    }
    assert rate["route_intercept"] >= rate["proportional_navigation"] > 0.3, rate


def test_pursuit_intercept_adds_the_meeting_point_and_when_it_is_due(scenarios):
    env = make_env(V10, scenarios=scenarios, num_envs=5, split="val")
    route = make_env(V10, "observation=pursuit_route", scenarios=scenarios, num_envs=5,
                     split="val")  # fmt: skip
    td, base = env.reset(), route.reset()
    assert td["observation"].shape == (5, 20)
    names = [f["name"] for f in env.obs_fn.features()[10:14]]
    assert names == ["(intercept - p_own).x", "(intercept - p_own).y", "(intercept - p_own).z",
                     "t_intercept"]  # fmt: skip
    for _ in range(20):
        obs, own = td["observation"], td["positions"][:, 0]
        torch.testing.assert_close(obs[:, [*range(10), *range(14, 20)]], base["observation"])
        aim, due, _ = env.meeting(env.dynamics.position, env.dynamics.velocity)
        torch.testing.assert_close(obs[:, 10:13], aim[:, 0] - own)
        torch.testing.assert_close(obs[:, 13], due[:, 0])
        action = torch.full((5, 3), 0.3)
        td = env.step(td.set("action", action))["next"]
        base = route.step(base.set("action", action))["next"]
    check_env_specs(env)


def test_pursuit_conform_adds_how_the_defender_departs_from_its_route(scenarios):
    env = make_env(V11, scenarios=scenarios, num_envs=8, split="val")
    base = make_env(V10, scenarios=scenarios, num_envs=8, split="val")
    td, ref = env.reset(), base.reset()
    assert td["observation"].shape == (8, 24) and env.nn_defender.any() and ~env.nn_defender.all()
    names = [f["name"] for f in env.obs_fn.features()[14:18]]
    assert names == ["route_residual.x", "route_residual.y", "route_residual.z",
                     "route_deviation"]  # fmt: skip
    assert env.obs_fn.features()[17]["unit"] == "m/s^2"
    lag, dt = torch.tensor([0.9, 0.9, 0.35]), env.control_period
    blend = 1 - math.exp(-dt / 1.0)  # conformity_time
    deviation = torch.zeros(8)
    for _ in range(40):
        obs = td["observation"]
        torch.testing.assert_close(obs[:, [*range(14), *range(18, 24)]], ref["observation"])
        p, v = td["positions"][:, 1], td["velocities"][:, 1]
        follow = follow_route(p, td["setpoints"][:, 0], td["route_done"][:, 0],
                              td["max_speed"][:, 1], env.setpoint_gain)  # fmt: skip
        caught = td["caught"][:, 0]  # a defender caught before the step holds: no residual
        action = torch.full((8, 3), 0.3)
        td = env.step(td.set("action", action))["next"]
        ref = base.step(ref.set("action", action))["next"]
        # The measured acceleration less a first-order lag's mean over the control period.
        residual = td["accelerations"][:, 1] - (follow - v) * (1 - torch.exp(-dt / lag)) / dt
        residual[caught] = 0.0
        deviation = deviation + blend * (residual.norm(dim=-1) - deviation)
        torch.testing.assert_close(td["observation"][:, 14:17], residual)
        torch.testing.assert_close(td["observation"][:, 17], deviation)
    check_env_specs(env)


def test_a_route_flyer_keeps_a_small_deviation_an_evader_does_not(tmp_path, write_small_set):
    # Flown against the route-intercept law: a setpoints defender follows its command as the
    # observation's lags predict it; the defender network leaves its route to evade.
    median = {}
    for kind, mix in (("route", "{setpoints: 1, nn: 0}"), ("nn", "{setpoints: 0, nn: 1}")):
        scenarios = write_small_set(tmp_path / kind, f"scenario.strategy_mix={mix}")
        env = make_env(V11, scenarios=scenarios, num_envs=16, split="val")
        law, td, seen = make_scripted_policy("route_intercept", env), env.reset(), []
        for step in range(150):
            td = env.step(law(td))["next"]
            playing = ~td["done"][:, 0] & ~td["caught"][:, 0]
            if step >= 20:  # after the take-off
                seen.append(td["observation"][playing, 17])
        median[kind] = torch.cat(seen).median().item()
    assert median["route"] < 0.5 < 1.5 < median["nn"], median


def test_pursuit_conform_refuses_a_bad_route_lag_and_a_defender(scenarios):
    for lag in ("[0.9,0.9]", "0.9", "[0.9,0.9,-1]"):
        with pytest.raises(ConfigError, match="observation.route_lag: must be 3 finite numbers"):
            make_env(V11, f"observation.route_lag={lag}", scenarios=scenarios, num_envs=2)
    # Its own options and, passed on, those of the observation it extends.
    with pytest.raises(ConfigError, match="observation.bogus: unknown key; valid: name, "
                       "conformity_time, route_lag, team_sight, position_scale, "
                       "velocity_scale"):  # fmt: skip
        make_env(V11, "+observation.bogus=1", scenarios=scenarios, num_envs=2)
    with pytest.raises(ConfigError, match="observation.team_sight: must be true or false"):
        make_env(V11, "observation.team_sight=3", scenarios=scenarios, num_envs=2)
    with pytest.raises(ConfigError, match="^observation: pursuit_conform reads the defender's"):
        make_env("drone=defender_v1", "observation=pursuit_conform", scenarios=scenarios,
                 num_envs=2)  # fmt: skip
    with pytest.raises(ConfigError, match="observation.conformity_time"):
        make_env(V11, "observation.conformity_time=0", scenarios=scenarios, num_envs=2)


@pytest.mark.parametrize(
    "option", ["action=route_law", "observation=pursuit_intercept", "observation=pursuit_conform"]
)
def test_the_meeting_point_is_an_attackers(scenarios, option):
    with pytest.raises(ConfigError, match="attacker"):
        make_env("drone=defender_v1", option, scenarios=scenarios, num_envs=2)


@pytest.mark.parametrize("key", ["homing_time", "start_lag", "horizon"])
def test_the_route_law_refuses_a_negative_time(scenarios, key):
    with pytest.raises(ConfigError, match=rf"^action.{key}: .*-1"):
        make_env(V10, f"action.{key}=-1", scenarios=scenarios, num_envs=2)
    with pytest.raises(ConfigError, match=rf"^route_intercept.{key}: .*inf"):
        make_scripted_policy("route_intercept", make_env(PLAIN, scenarios=scenarios),
                             **{key: math.inf})  # fmt: skip


# A correction gated on the route deviation (attacker_v13) --------------------------------

V13 = "drone=attacker_v13"  # attacker_v12 with the correction gated on the route deviation


def test_the_gate_scales_the_correction_by_the_route_deviation():
    from rlplat.envs.components import RouteLawAction

    gated = RouteLawAction(gate_low=1.5, gate_high=2.5)
    plain = RouteLawAction()
    action = torch.tensor([[1.0, -1.0, 0.5]]).expand(4, 3)
    guidance = torch.full((4, 3), 0.1)
    speed = torch.full((4,), 4.0)
    deviation = torch.tensor([0.0, 1.5, 2.0, 9.0])
    flown = gated(action, speed, guidance, deviation)
    reach = torch.tensor([0.0, 0.0, 0.5, 1.0]).unsqueeze(-1)
    torch.testing.assert_close(flown, plain(action * reach, speed, guidance))
    torch.testing.assert_close(flown[:2], (guidance * 4.0)[:2])  # shut: the law alone
    with pytest.raises(ValueError, match="needs the route deviation"):
        gated(action, speed, guidance)


def test_a_gated_env_flies_the_correction_scaled_by_the_deviation_it_observed(scenarios):
    # The env gates with the route deviation the policy saw: the same rollout as an ungated
    # env flown with the action already scaled by that observation's gate.
    n, lo, hi = len(scenarios.split("val")), 0.5, 3.0
    gated = make_env(V11, f"action.gate_low={lo}", f"action.gate_high={hi}", scenarios=scenarios,
                     num_envs=n, split="val")  # fmt: skip
    plain = make_env(V11, scenarios=scenarios, num_envs=n, split="val")
    names = [f["name"] for f in gated.obs_fn.features()]
    deviation = names.index("route_deviation")  # the observation's raw m/s^2 (scaled in the net)
    g = torch.Generator().manual_seed(0)
    a, b = gated.reset(), plain.reset()
    fractional = 0
    for _ in range(60):
        action = torch.rand(n, 3, generator=g) * 2 - 1
        d = a["observation"][:, deviation]
        reach = ((d - lo) / (hi - lo)).clamp(0, 1)
        fractional += int(((reach > 0) & (reach < 1)).sum())
        a = gated.step(a.set("action", action))["next"]
        b = plain.step(b.set("action", action * reach.unsqueeze(-1)))["next"]
        assert torch.equal(a["positions"], b["positions"])
    assert fractional > 0  # the gate was partly open somewhere


def test_gate_unreachable_opens_the_gate_where_no_meeting_point_is_reachable(scenarios):
    from rlplat.envs.components import RouteLawAction

    opens = RouteLawAction(gate_low=1.5, gate_high=2.5, gate_unreachable=True)
    deviation = torch.tensor([0.0, 2.0, 0.0, 2.0])
    reachable = torch.tensor([True, True, False, False])
    assert opens.reach(deviation, reachable).squeeze(-1).tolist() == [0.0, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError, match="gate_unreachable needs the meeting point"):
        opens.reach(deviation)
    # In the env: a shut gate (the law alone) but where the observed state's meeting point is
    # out of reach, there the whole correction; an ungated env flown with the action masked
    # the same way flies the same paths.
    n = len(scenarios.split("val"))
    shut = ("action.gate_low=1000", "action.gate_high=1001", "action.gate_unreachable=true")
    gated = make_env(V11, *shut, scenarios=scenarios, num_envs=n, split="val")
    plain = make_env(V11, scenarios=scenarios, num_envs=n, split="val")
    g = torch.Generator().manual_seed(2)
    a, b = gated.reset(), plain.reset()
    opened = 0
    for _ in range(60):
        action = torch.rand(n, 3, generator=g) * 2 - 1
        out_of_reach = ~gated._meeting[2].reshape(n)  # of the state the policy observes
        opened += int(out_of_reach.sum())
        a = gated.step(a.set("action", action))["next"]
        b = plain.step(b.set("action", action * out_of_reach.unsqueeze(-1)))["next"]
        assert torch.equal(a["positions"], b["positions"])
    assert opened > 0  # some defender was out of reach
    with pytest.raises(ConfigError, match="^action.gate_unreachable: opens the gate where no "
                       "meeting point is reachable, and this action has no gate"):  # fmt: skip
        make_env(V11, "action.gate_unreachable=true", scenarios=scenarios, num_envs=2)


def test_a_gated_correction_flies_only_its_law_where_the_defender_keeps_its_route(scenarios):
    n = len(scenarios.split("val"))
    shut = make_env(V11, "action.gate_low=1000", "action.gate_high=1001", scenarios=scenarios,
                    num_envs=n, split="val")  # fmt: skip
    law = make_env(V11, scenarios=scenarios, num_envs=n, split="val")
    a, b = shut.reset(), law.reset()
    g = torch.Generator().manual_seed(1)
    for _ in range(40):
        a = shut.step(a.set("action", torch.rand(n, 3, generator=g) * 2 - 1))["next"]
        b = law.step(b.set("action", torch.zeros(n, 3)))["next"]
        assert torch.equal(a["positions"], b["positions"])
    # Through the gate the route-intercept law flies (a zero correction), no other script.
    assert make_scripted_policy("route_intercept", shut)(shut.reset())["action"].abs().max() == 0
    with pytest.raises(ConfigError, match="proportional_navigation cannot be flown through "
                       "action=route_law with a gate"):  # fmt: skip
        make_scripted_policy("proportional_navigation", shut)


def test_the_gate_refuses_a_bad_range_and_an_observation_without_the_deviation(scenarios):
    for knobs, match in (
        (["action.gate_low=2", "action.gate_high=1"], r"^action.gate_high: must be > "),
        (["action.gate_low=1", "action.gate_high=1"], r"^action.gate_high: must be > "),
        (["action.gate_low=1"], r"^action.gate_high: 0 turns the gate off"),
        (
            ["action.gate_low=-1", "action.gate_high=1"],
            r"^action.gate_low: must be a finite number >= 0",
        ),
    ):
        with pytest.raises(ConfigError, match=match):
            make_env(V11, *knobs, scenarios=scenarios, num_envs=2)
    with pytest.raises(ConfigError, match="^action.gate_high: the gate reads the route "
                       "deviation that observation=pursuit_conform reports; this run's "
                       "observation is pursuit_intercept$"):  # fmt: skip
        make_env(V13, "observation=pursuit_intercept", scenarios=scenarios, num_envs=2)


def test_the_gated_bundle_starts_from_its_law_and_states_the_gate_in_its_card(scenarios):
    env = make_env(V13, scenarios=scenarios, num_envs=2)
    assert (env.action_fn.gate_low, env.action_fn.gate_high) == (1.5, 2.5)
    assert (env.action_fn.homing_time, env.action_fn.start_lag) == (0.5, 0.5)  # attacker_v12's
    card = env.action_fn.card()
    assert card["guidance"]["gate"] == {"low": 1.5, "high": 2.5, "unreachable_opens": False}
    assert "gate(d) = clamp((d - 1.5) / 1, 0, 1)" in card["unit"]
    assert any(line.startswith("GATED") for line in env.action_fn.describe())
    assert "gate" not in make_env(V11, scenarios=scenarios, num_envs=2).action_fn.card()["guidance"]


def test_a_checkpoint_flies_only_with_the_look_ahead_it_was_trained_with():
    from types import SimpleNamespace

    from rlplat.agents.checkpoint import check_route_path, route_path_interface

    def env(horizon):
        return SimpleNamespace(computes_meeting=True, route_flight=setpoint_flight(1.0, 1.0),
                               meeting_lag=0.5, law_horizon=horizon)  # fmt: skip

    trained = {"interface": {"route_path": route_path_interface(env(120.0))}}
    check_route_path(trained, env(120.0), "best.pt", "evaluate")
    with pytest.raises(ConfigError, match=r"'horizon': 120.0}, this env's .*'horizon': None}"):
        check_route_path(trained, env(None), "best.pt", "evaluate")
    # Saved before the look-ahead was a setting: the law looked as far as the time limit.
    del trained["interface"]["route_path"]["horizon"]
    check_route_path(trained, env(None), "best.pt", "evaluate")
    with pytest.raises(ConfigError, match="'horizon': None}, this env's"):
        check_route_path(trained, env(120.0), "best.pt", "evaluate")
