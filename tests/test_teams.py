"""Several drones: k attackers and m defenders in one env, a shared policy per learning role."""

import inspect
import itertools
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from rlplat import make_env
from rlplat.agents.policies import make_scripted_policy
from rlplat.agents.transitions import agent_rows
from rlplat.envs.components import OBSERVATIONS, DroneView, sight_margin
from rlplat.envs.kinematics import nearest, targets
from rlplat.errors import ConfigError
from rlplat.eval.episodes import evaluate
from rlplat.scenarios import ScenarioSet, write_scenario_set

SIZES = ("scenario.n_train=32", "scenario.n_val=16", "scenario.n_test=16")
TEAMS = list(itertools.product((1, 2), (1, 2)))


@pytest.fixture(scope="module")
def team_sets(tmp_path_factory, make_spec) -> dict[tuple[int, int], ScenarioSet]:
    """A small scenario set per (attackers, defenders) in {1, 2}^2."""
    sets = {}
    for k, m in TEAMS:
        path = tmp_path_factory.mktemp(f"teams_{k}v{m}")
        write_scenario_set(
            make_spec(*SIZES, f"scenario.attackers={k}", f"scenario.defenders={m}"), path
        )
        sets[k, m] = ScenarioSet.load(path)
    return sets


@pytest.fixture(scope="module")
def lone_run(team_sets, tmp_path_factory, tiny_run) -> str:
    """A tiny run trained alone (1 vs 1), read (never written) by the tests that fly it in a
    team."""
    return tiny_run(team_sets[1, 1], tmp_path_factory.mktemp("lone") / "run")["run_dir"]


@pytest.mark.parametrize("drone", ["attacker_v3", "defender_v1"])
@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_specs_of_every_team_size(team_sets, drone, k, m):
    env = make_env(f"drone={drone}", scenarios=team_sets[k, m], num_envs=3)
    check_env_specs(env, seed=0)
    td = env.reset()
    assert td["positions"].shape == (3, k + m, 3)
    assert td["caught"].shape == td["waypoint"].shape == (3, m)
    # Each drone sees every opponent and its team-mates: a block per other drone, which says
    # whether that drone is still in play where defenders can be caught one by one.
    role = drone.split("_")[0]  # attacker_v3 -> attacker
    team, others, own = (k, m, 3) if role == "attacker" else (m, k, 6)  # eq. 1 / route_state
    obs_dim = own + (6 + (m > 1)) * (others + team - 1)
    if team == 1:
        assert env.group is None and td["observation"].shape == (3, obs_dim)
        return
    assert env.action_key == (role, "action")
    assert td[role, "observation"].shape == (3, team, obs_dim)
    assert td[role, "distance"].shape == (3, team, 1)
    if role == "defender":
        assert td["defender", "caught"].shape == (3, team, 1)


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_pursuit_conform_reads_each_attackers_nearest_defender(team_sets, k, m):
    env = make_env("drone=attacker_v11", scenarios=team_sets[k, m], num_envs=3)
    check_env_specs(env, seed=0)
    obs_key = "observation" if k == 1 else (env.group, "observation")
    td = env.reset()
    assert td[obs_key].shape[-1] == 18 + (6 + (m > 1)) * (k + m - 1)
    action = torch.full(env.full_action_spec[env.action_key].shape, 0.5)
    for _ in range(15):
        td = env.step(td.set(env.action_key, action))["next"]
        obs = td[obs_key].reshape(3, k, -1)
        p = env.dynamics.position
        near = nearest(p[:, :k], p[:, k:], targets(env.caught))  # (3, k)
        residual = env.route_residual.gather(1, near.unsqueeze(-1).expand(3, k, 3))
        torch.testing.assert_close(obs[..., 14:17], residual)
        torch.testing.assert_close(obs[..., 17], env.route_deviation.gather(1, near))


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_team_sight_says_which_attacker_the_defender_sees(team_sets, k, m):
    sight = make_env("drone=attacker_v11", "observation.team_sight=true",
                     scenarios=team_sets[k, m], num_envs=3)  # fmt: skip
    plain = make_env("drone=attacker_v11", scenarios=team_sets[k, m], num_envs=3)
    check_env_specs(sight, seed=0)
    obs_key = "observation" if k == 1 else (sight.group, "observation")
    sight.set_seed(0)
    plain.set_seed(0)
    td, td_plain = sight.reset(), plain.reset()
    if k == 1:  # nothing to compare with: the 1-vs-1 observation, unchanged
        torch.testing.assert_close(td[obs_key], td_plain[obs_key], rtol=0, atol=0)
        return
    assert td[obs_key].shape[-1] == td_plain[obs_key].shape[-1] + 1
    assert sight.obs_fn.features()[18]["name"] == "sight_margin"
    action = torch.full(sight.full_action_spec[sight.action_key].shape, 0.5)
    for _ in range(5):
        td = sight.step(td.set(sight.action_key, action))["next"]
        td_plain = plain.step(td_plain.set(plain.action_key, action))["next"]
        # The rest of the observation is pursuit_conform's, value for value.
        rest = torch.cat([td[obs_key][..., :18], td[obs_key][..., 19:]], -1)
        torch.testing.assert_close(rest, td_plain[obs_key], rtol=0, atol=0)
        p = sight.dynamics.position
        near = nearest(p[:, :k], p[:, k:], targets(sight.caught))  # (3, k)
        defender = p[:, k:].gather(1, near.unsqueeze(-1).expand(3, k, 3))  # (3, k, 3)
        to_own = (defender - p[:, :k]).norm(dim=-1)
        to_mate = (defender.unsqueeze(2) - p[:, :k].unsqueeze(1)).norm(dim=-1)  # (3, k, k)
        to_mate = to_mate.masked_fill(torch.eye(k, dtype=torch.bool), float("inf"))
        margin = td[obs_key][..., 18]
        torch.testing.assert_close(margin, to_mate.amin(-1) - to_own)
        if m == 1:  # exactly one attacker is the lone defender's nearest (ties aside)
            assert ((margin > 0).sum(-1) == 1).all()


def test_sight_margin_picks_the_nearest_defender_in_play():
    zero = torch.zeros(1, 3)
    defenders = torch.tensor([[[3.0, 0.0, 0.0], [0.0, 10.0, 0.0]]])  # (1, 2, 3)
    mate = torch.tensor([[[0.0, 4.0, 0.0]]])  # 6 m from the second defender, 5 m from the first

    def margin(in_play):
        view = DroneView(zero, zero, defenders, torch.zeros_like(defenders), mate_position=mate,
                         mate_velocity=torch.zeros_like(mate), other_in_play=in_play)  # fmt: skip
        return sight_margin(view).item()

    assert margin(torch.tensor([[True, True]])) == pytest.approx(5.0 - 3.0)
    assert margin(torch.tensor([[False, True]])) == pytest.approx(6.0 - 10.0)
    assert margin(torch.tensor([[False, False]])) == pytest.approx(5.0 - 3.0)  # all: as the env


@pytest.mark.parametrize("drone", ["attacker_v8", "defender_v1"])
@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_pursuit_accel_blocks_hold_each_other_drones_acceleration(team_sets, drone, k, m):
    env = make_env(f"drone={drone}", "observation=pursuit_accel", scenarios=team_sets[k, m],
                   num_envs=3)  # fmt: skip
    check_env_specs(env, seed=0)
    attacker = drone.startswith("attacker")
    team = k if attacker else m
    obs_key = "observation" if team == 1 else (env.group, "observation")
    block = 9 + (m > 1)  # p, v, a (and the in-play flag where defenders can leave play)
    td = env.reset()
    assert td[obs_key].shape[-1] == 4 + block * (k + m - 1)
    action = torch.full(env.full_action_spec[env.action_key].shape, 0.5)
    td = env.step(td.set(env.action_key, action))["next"]
    obs = td[obs_key].reshape(3, team, -1)
    a = td["accelerations"]  # (3, k + m, 3): attackers first
    for i in range(team):
        own = i if attacker else k + i
        opponents = range(k, k + m) if attacker else range(k)
        mates = range(k) if attacker else range(k, k + m)
        others = [*opponents, *(d for d in mates if d != own)]
        for b, d in enumerate(others):
            at = 4 + b * block + 6
            torch.testing.assert_close(obs[:, i, at : at + 3], a[:, d])
    # The drones' accelerations differ: a block read from the wrong drone shows.
    assert (a - a[:, :1]).abs().amax() > 0.01


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_pursuit_world_gives_each_attacker_its_own_world_position(team_sets, k, m):
    env = make_env("drone=attacker_v8", "observation=pursuit_world", scenarios=team_sets[k, m],
                   num_envs=3)  # fmt: skip
    check_env_specs(env, seed=0)
    obs_key = "observation" if k == 1 else (env.group, "observation")
    td = env.reset()
    for _ in range(2):
        obs = td[obs_key].reshape(3, k, -1)
        assert obs.shape[-1] == 7 + (6 + (m > 1)) * (k + m - 1)  # own: v, max speed, p_own
        torch.testing.assert_close(obs[..., 4:7], td["positions"][:, :k])  # attackers first
        action = torch.full(env.full_action_spec[env.action_key].shape, 0.5)
        td = env.step(td.set(env.action_key, action))["next"]


def test_a_caught_learning_defender_stops_and_earns_nothing_more(team_sets):
    env = make_env("drone=defender_v1", scenarios=team_sets[2, 2], split="val", num_envs=16)
    env.set_seed(0)
    hover = env.rollout(300, lambda td: td.update(env.full_action_spec.zero()),
                        break_when_any_done=False)  # fmt: skip
    nxt = hover["next"]
    caught, before = nxt["defender", "caught"], hover["defender", "caught"]
    assert (before & ~nxt["done"].unsqueeze(-1)).any(), "some defender should be caught early"
    out = before & ~hover["done"].unsqueeze(-1)  # caught before the step, same episode
    assert (nxt["defender", "reward"][out] == 0).all()
    assert (nxt["defender", "reward"][~caught] != 0).any()
    assert torch.equal(nxt["caught"], caught.squeeze(-1))
    # Each defender sees whether its team-mate is still in play (the flag closing its block).
    mate_flag = nxt["defender", "observation"][..., 6 + 7 * 2 + 6]  # after 2 attackers' blocks
    assert torch.equal(mate_flag, (~caught.squeeze(-1)).flip(-1).float())


@pytest.mark.parametrize(("k", "m"), TEAMS)
def test_same_seed_same_rollout(team_sets, k, m):
    def run(seed):
        env = make_env("env.scenario_order=shuffled", scenarios=team_sets[k, m], num_envs=4)
        env.set_seed(seed)
        torch.manual_seed(0)  # the random actions
        return env.rollout(30, break_when_any_done=False)

    a, b, c = run(1), run(1), run(2)
    assert torch.equal(a["next", "positions"], b["next", "positions"])
    assert not torch.equal(a["scenario_index"], c["scenario_index"])


def test_the_observation_holds_team_mates_relative_state(team_sets):
    env = make_env("drone=attacker_v3", scenarios=team_sets[2, 1], num_envs=2)  # eq. 1 blocks
    td = env.reset()
    p = td["positions"]
    obs = td["attacker", "observation"]  # [v_own, p_d - p_a, v_d - v_a, p_mate - p_a, v_mate - ...]
    torch.testing.assert_close(obs[:, 0, 3:6], p[:, 2] - p[:, 0])
    torch.testing.assert_close(obs[:, 1, 3:6], p[:, 2] - p[:, 1])
    torch.testing.assert_close(obs[:, 0, 9:12], p[:, 1] - p[:, 0])
    torch.testing.assert_close(obs[:, 1, 9:12], p[:, 0] - p[:, 1])


def test_a_caught_defender_leaves_play_and_the_last_capture_ends_the_episode(team_sets):
    env = make_env("drone=attacker_v3", scenarios=team_sets[2, 2], split="val", num_envs=16)
    env.set_seed(0)
    rollout = env.rollout(600, make_scripted_policy("pure_pursuit", env), break_when_any_done=False)
    caught, done = rollout["next", "caught"], rollout["next", "done"].squeeze(-1)
    partly = caught.any(-1) & ~caught.all(-1) & ~done
    assert partly.any(), "pure pursuit by two attackers should catch one defender before both"
    # The episode goes on after the first capture and ends (terminated) on the second.
    # (or when a defender, or every attacker, is on the ground)
    on_ground = rollout["next", "positions"][..., 2] <= 0
    down = rollout["next", "attacker", "down"].squeeze(-1)
    assert (down | ~on_ground[..., :2]).all()  # an attacker on the ground is down
    crashed = on_ground[..., 2:].any(-1) | down.all(-1)
    assert torch.equal(rollout["next", "terminated"].squeeze(-1), caught.all(-1) | crashed)
    assert (rollout["next", "captured"].squeeze(-1) == caught.all(-1)).all()
    # Each attacker sees which defender is still in play: the flag closing its block.
    obs = rollout["next", "attacker", "observation"]  # [v_own, (p, v, in play) per other drone]
    for j in range(2):
        flag = obs[..., 3 + 7 * j + 6]
        assert torch.equal(flag, (~caught[..., j]).float().unsqueeze(-1).expand_as(flag))
    # A caught defender brakes to a hover where it is while the episode goes on.
    first = partly & ~torch.cat([partly[:, :1] & False, partly[:, :-1]], 1)
    checked = 0
    for env_i, t in first.nonzero().tolist():
        if done[env_i, t : t + 40].any() or t + 40 > done.shape[1]:
            continue
        j = int(caught[env_i, t].int().argmax())
        p = rollout["next", "positions"][env_i, t : t + 40, 2 + j]
        assert (p[39] - p[30]).norm() < 0.1 * (p[9] - p[0]).norm()
        checked += 1
    assert checked


def test_a_downed_attacker_holds_and_its_team_mate_flies_on(team_sets):
    env = make_env("drone=attacker_v3", scenarios=team_sets[2, 1], split="val", num_envs=16)
    env.set_seed(0)
    pursue = make_scripted_policy("pure_pursuit", env)

    def dive_first(td):  # the first attacker dives east at full speed, its mate pursues
        action = pursue(td)[env.action_key].clone()
        action[:, 0] = torch.tensor([1.0, 0.0, -1.0])  # on the ground it would slide on east
        return td.set(env.action_key, action)

    rollout = env.rollout(400, dive_first, break_when_any_done=False)
    nxt, done = rollout["next"], rollout["next", "done"].squeeze(-1)
    down, before = nxt["attacker", "down"].squeeze(-1), rollout["attacker", "down"].squeeze(-1)
    low = nxt["positions"][..., :2, 2] <= env.ground_altitude
    ended = torch.cat([torch.zeros_like(done[:, :1]), done[:, :-1]], 1).cummax(1).values
    first = ~ended  # the steps of each env's first episode
    assert torch.equal(down[first], (low.cummax(1).values)[first])
    fell = down[..., 0] & ~before[..., 0] & first
    assert fell.sum() >= 12, "the diving attacker should land in most first episodes"
    # Its landing does not end the episode: the mate flies on and catches some defenders.
    assert (~done[fell] | nxt["captured"].squeeze(-1)[fell]).all()
    captured_after = nxt["captured"].squeeze(-1) & before[..., 0] & first
    assert captured_after.any(), "the pursuing mate should catch a defender after the landing"
    # The downed attacker brakes to a hold where it landed (flying on it would slide east at
    # full speed) and earns nothing after its landing step; on it it pays the crash
    # (ground_contact) that its mate does not.
    on_ground = before[..., 0] & first
    step = (nxt["positions"][..., 0, :] - rollout["positions"][..., 0, :]).norm(dim=-1)
    full = env.control_period * env.max_speed[:, 0].unsqueeze(-1).expand_as(step)
    settled = on_ground & (on_ground.cumsum(1) > 50)  # 5 s after the landing
    assert settled.sum() > 100
    assert (step[settled] < 0.05 * full[settled]).all()
    reward = nxt["attacker", "reward"].squeeze(-1)
    assert (reward[..., 0][on_ground] == 0).all()
    crash = env.reward_fn.weights["ground_contact"]
    assert (reward[..., 0][fell] - reward[..., 1][fell] < 0.5 * crash).all()
    # Evaluated: an episode the mate flies on to its end is no crash, caught or not, and a
    # defender it does not catch evades by the route it flew.
    flown = evaluate(env, dive_first)
    assert not flown.grounded.any() and not flown.captured.all()
    missed = ~flown.captured
    assert torch.equal(flown.evasion[missed], flown.route_fraction[missed])

    # Both attackers diving: the episode ends (terminated) when the second one lands.
    def dive_both(td):
        action = torch.zeros(env.full_action_spec[env.action_key].shape)
        action[..., 2] = -1.0
        return td.set(env.action_key, action)

    env.set_seed(0)
    rollout = env.rollout(400, dive_both, break_when_any_done=False)
    nxt, done = rollout["next"], rollout["next", "done"].squeeze(-1)
    first = ~torch.cat([torch.zeros_like(done[:, :1]), done[:, :-1]], 1).cummax(1).values
    down = nxt["attacker", "down"].squeeze(-1)
    ends = down.all(-1) | nxt["captured"].squeeze(-1)
    assert torch.equal(nxt["terminated"].squeeze(-1)[first], ends[first])
    assert (down.any(-1) & ~down.all(-1) & first).any(), "one attacker should land first"
    flown = evaluate(env, dive_both)  # every attacker down: a crash, unless caught before
    assert torch.equal(flown.grounded, ~flown.captured) and flown.grounded.any()


def test_team_transitions_are_one_row_per_drone():
    envs, steps, agents = 2, 3, 2
    obs = torch.arange(envs * steps * agents * 4, dtype=torch.float32)
    obs = obs.reshape(envs, steps, agents, 4)
    done = torch.zeros(envs, steps, 1, dtype=torch.bool)
    done[1, 2] = True

    def team(x, k=1):
        return {"observation": x, "action": x[..., :3], "distance": x[..., :1] * k}

    batch = TensorDict(
        {
            "attacker": TensorDict(team(obs), batch_size=(envs, steps, agents)),
            "next": {
                "attacker": TensorDict(
                    {**team(obs + 1, 2), "reward": obs[..., :1] * 10},
                    batch_size=(envs, steps, agents),
                ),
                "done": done,
                "terminated": done,
            },
        },
        batch_size=(envs, steps),
    )
    rows = agent_rows(batch, "attacker")
    assert rows.shape == (envs * agents, steps)
    for e, a in itertools.product(range(envs), range(agents)):
        row = rows[e * agents + a]
        assert torch.equal(row["observation"], obs[e, :, a])
        assert torch.equal(row["next", "reward"], obs[e, :, a, :1] * 10)
        assert torch.equal(row["next", "distance"], (obs[e, :, a, :1] + 1) * 2)
        assert torch.equal(row["next", "done"], done[e])


@pytest.mark.parametrize(("group", "out"), [("defender", "caught"), ("attacker", "down")])
def test_a_drone_out_of_play_ends_its_own_rows(group, out):
    envs, steps, agents = 1, 4, 2
    obs = torch.zeros(envs, steps, agents, 3)
    caught = torch.zeros(envs, steps + 1, agents, 1, dtype=torch.bool)
    caught[0, 2:, 1] = True  # drone 1 leaves play in step 1 (entries after it say so)
    done = torch.zeros(envs, steps, 1, dtype=torch.bool)

    def team(t, extra=None):
        x = {"observation": obs, "action": obs, "distance": obs[..., :1], out: caught[:, t]}
        return TensorDict({**x, **(extra or {})}, batch_size=(envs, steps, agents))

    batch = TensorDict(
        {
            group: team(slice(0, steps)),
            "next": {
                group: team(slice(1, None), {"reward": obs[..., :1]}),
                "done": done,
                "terminated": done,
            },
        },
        batch_size=(envs, steps),
    )
    rows = agent_rows(batch, group)
    assert rows["alive"].squeeze(-1).tolist() == [[True] * 4, [True, True, False, False]]
    assert rows["next", "terminated"].squeeze(-1).tolist() == [
        [False] * 4,
        [False, True, True, True],
    ]


def test_pure_pursuit_team_catches_more_than_random(team_sets):
    env = make_env("action=velocity", scenarios=team_sets[2, 1], split="val", num_envs=16)
    chase = evaluate(env, make_scripted_policy("pure_pursuit", env))

    def random(td):
        return td.update(env.full_action_spec.rand())

    torch.manual_seed(0)
    assert chase.capture_rate > evaluate(env, random).capture_rate


def test_an_evaluation_measures_how_near_the_attackers_came_to_each_other(team_sets):
    from rlplat.eval.tables import NEAR_MISS_M, episode_rows, summarize

    env = make_env("action=velocity", scenarios=team_sets[2, 1], split="val", num_envs=16)
    chase = evaluate(env, make_scripted_policy("pure_pursuit", env), record=True)
    # From the recorded paths: the least distance between the two attackers while both fly.
    a, b = chase.positions[:, :, 0], chase.positions[:, :, 1]
    up = (a[..., 2] > env.ground_altitude) & (b[..., 2] > env.ground_altitude)
    expected = (a - b).norm(dim=-1).masked_fill(~up, float("inf")).amin(1)
    torch.testing.assert_close(chase.attacker_separation, expected)
    # Both chasing one defender, they close on each other: pure pursuit converges.
    starts = team_sets[2, 1].split("val")["attacker_start"]
    assert (chase.attacker_separation < (starts[:, 0] - starts[:, 1]).norm(dim=-1)).all()
    rows = episode_rows(chase, team_sets[2, 1], "val", env.routes.cpu(), 2)
    assert [r["attacker_separation_m"] for r in rows] == chase.attacker_separation.tolist()
    sep = summarize(rows, list(env.reward_fn.weights), [1.0])["attacker_separation"]
    assert sep["least_m"] == pytest.approx(chase.attacker_separation.min().item())
    assert sep["near_misses"] == int((chase.attacker_separation < NEAR_MISS_M).sum())
    # One attacker: no team-mate to come near, no column and no summary entry.
    one = make_env("action=velocity", "env.attackers=1", scenarios=team_sets[2, 1], split="val",
                   num_envs=16)  # fmt: skip
    alone = evaluate(one, make_scripted_policy("pure_pursuit", one))
    assert alone.attacker_separation.isnan().all()
    rows = episode_rows(alone, team_sets[2, 1], "val", one.routes.cpu(), 1)
    assert "attacker_separation_m" not in rows[0]
    assert "attacker_separation" not in summarize(rows, list(one.reward_fn.weights), [1.0])


@pytest.mark.slow
def test_a_learned_two_vs_one_policy_beats_a_random_one(easy_pursuit, tmp_path, record_property):
    from omegaconf import OmegaConf

    from rlplat.experiment.config import compose_config
    from rlplat.experiment.factory import build_env
    from rlplat.experiment.training import train
    from rlplat.scenarios import ScenarioSpec

    spec = compose_config("scenarios", ["out_dir=unused", *easy_pursuit, "scenario.attackers=2"])
    write_scenario_set(ScenarioSpec.from_dict(OmegaConf.to_container(spec.scenario)), tmp_path)
    cfg = compose_config(
        "train",
        [
            "drone=attacker_v3",  # from a random actor (attacker_v4 starts at the law)
            f"scenarios_dir={tmp_path}",
            "env.time_limit=20",
            "train.max_minutes=null",  # frames only: the same budget on a slower machine
            # After 4,096 frames of learning it captured about half of the split on a 2-core CPU
            # (0.48 with one thread, 0.69 with two), at 12,288 frames 0.92 (16,384: 0.97); the
            # bar is a random policy's rate (0.02) + 0.2.
            "train.total_frames=12288",
            "train.eval_every_frames=4096",
            "train.progress=false",
            "algo.init_policy=random",  # nothing scripted: what it catches, it learned
            "algo.init_random_frames=4096",
            "algo.compile=false",
        ],
    )
    summary = train(cfg, run_dir=tmp_path / "run")
    assert summary["attackers"] == 2
    scenarios = ScenarioSet.load(tmp_path)
    env = build_env(
        cfg, scenarios=scenarios, split="val", num_envs=len(scenarios.split("val")),
        scenario_order="sequential",
    )  # fmt: skip
    torch.manual_seed(0)
    random = evaluate(env, lambda td: td.update(env.full_action_spec.rand())).capture_rate
    record_property("random_val_capture_rate", random)
    for key in ("frames", "best_val_capture_rate"):
        record_property(key, summary[key])
    assert summary["best_val_capture_rate"] >= random + 0.2, (summary, random)


def test_env_attackers_flies_the_first_attackers_of_each_scenario(team_sets):
    one = make_env("env.attackers=1", scenarios=team_sets[2, 1], split="val", num_envs=4)
    two = make_env(scenarios=team_sets[2, 1], split="val", num_envs=4)
    first, both = one.reset()["positions"], two.reset()["positions"]
    assert one.group is None and first.shape == (4, 2, 3)
    assert torch.equal(first, both[:, [0, 2]])  # the first attacker, the same defender
    for bad, error in (
        ("3", "the scenarios have 2"),
        ("0", "must be an integer >= 1 or null, got 0"),
        ("two", "must be an integer >= 1 or null, got 'two'"),
    ):
        with pytest.raises(ConfigError, match=f"env.attackers: .*{error}"):
            make_env(f"env.attackers={bad}", scenarios=team_sets[2, 1])


def test_the_gym_adapter_refuses_a_team(team_sets):
    from rlplat import make_gym_env

    with pytest.raises(ConfigError, match=r"gym adapter: flies one learning drone.*env.attackers"):
        make_gym_env(scenarios=team_sets[2, 1])
    with pytest.raises(ConfigError, match=r"defenders 2 \(scenario.defenders: valid 1\)"):
        make_gym_env("drone=defender_v1", scenarios=team_sets[1, 2])


def test_a_team_run_and_a_lone_run_evaluate_on_the_same_defenders(
    team_sets, tmp_path, tiny_run, lone_run, caplog
):
    import csv
    import logging

    from rlplat.experiment.evaluation import evaluate_run

    lone = lone_run
    team = tiny_run(team_sets[2, 1], tmp_path / "2v1")["run_dir"]
    kwargs = dict(plots=False, split="val")
    pair = evaluate_run(team, **kwargs).summary
    alone = evaluate_run(
        lone, scenarios_dir=team_sets[2, 1].path, attackers=1, out_dir=tmp_path / "e", **kwargs
    )
    assert (pair["attackers"], alone.summary["attackers"]) == (2, 1)
    assert pair["scenario_digest"] == alone.summary["scenario_digest"]

    def rows(path):
        with open(path / "episodes.csv") as f:
            return list(csv.DictReader(f))

    pair_rows, alone_rows = rows(Path(team) / "eval" / "val-best"), rows(alone.out_dir)
    assert "attacker1_max_speed" in pair_rows[0] and "attacker1_max_speed" not in alone_rows[0]
    assert "team_speed_ratio" not in alone_rows[0]
    assert "attacker_separation_m" in pair_rows[0] and "attacker_separation_m" not in alone_rows[0]
    assert pair["attacker_separation"]["episodes"] == len(pair_rows)
    for r in pair_rows:  # the fastest attacker of the pair over the defender (CSV: 6 digits)
        fastest = max(float(r["attacker_max_speed"]), float(r["attacker1_max_speed"]))
        ratio = fastest / float(r["defender_max_speed"])
        assert float(r["team_speed_ratio"]) == pytest.approx(ratio, rel=1e-5)
    assert any(r["team_speed_ratio"] != r["speed_ratio"] for r in pair_rows)
    same = ("scenario_id", "route", "defender_strategy", "defender_start_z", "attacker_start_x")
    assert [[r[c] for c in same] for r in pair_rows] == [[r[c] for c in same] for r in alone_rows]
    # A checkpoint flies only the team it was trained in.
    with pytest.raises(ConfigError, match=r"trained with attackers=2, this evaluation flies"):
        evaluate_run(team, attackers=1, out_dir=tmp_path / "f", **kwargs)
    refused = r"trained with attackers=1, this evaluation flies .*lone_in_team=true flies it"
    caplog.clear()
    with caplog.at_level(logging.WARNING), pytest.raises(ConfigError, match=refused):
        evaluate_run(lone, scenarios_dir=team_sets[2, 1].path, out_dir=tmp_path / "g", **kwargs)
    assert "anyway" not in caplog.text  # refused: no "evaluating anyway" before the error
    # The defenders are the set's alone (attackers= only flies fewer attackers).
    two = r"with defenders=1, this evaluation flies defenders=2 \(scenarios_dir\)$"
    with pytest.raises(ConfigError, match=two):
        evaluate_run(lone, scenarios_dir=team_sets[1, 2].path, out_dir=tmp_path / "d", **kwargs)
    with pytest.raises(ConfigError, match=r"^ensemble: .* was trained with attackers=1, "):
        evaluate_run(team, ensemble=[lone], out_dir=tmp_path / "e", **kwargs)
    # export.py chooses the team by its scenarios_dir alone: the refusal names only that.
    from rlplat.experiment.export import export_run

    only = r"^ckpt: .* with attackers=1, this export flies attackers=2 \(scenarios_dir\)$"
    with pytest.raises(ConfigError, match=only):
        export_run(lone, scenarios_dir=team_sets[2, 1].path, out_dir=tmp_path / "ex")
    assert not (tmp_path / "ex").exists()
    # Only a checkpoint trained alone flies each seat of a team.
    trained_in_a_team = r"^lone_in_team: .* trained alone .* trained in a team, with attackers=2$"
    with pytest.raises(ConfigError, match=trained_in_a_team):
        evaluate_run(team, lone_in_team=True, out_dir=tmp_path / "h", **kwargs)


@pytest.mark.parametrize("name", sorted(OBSERVATIONS))
@pytest.mark.parametrize(
    ("opponents", "mates", "team_flags", "lone_flags"),
    # (1, 1, True, False): a defender of two, whose flags come with its team-mate
    [(1, 1, False, False), (1, 2, False, False), (2, 1, True, True), (1, 1, True, False)],
)
def test_a_team_observation_holds_the_lone_one(name, opponents, mates, team_flags, lone_flags):
    # lone_features picks, from a team drone's observation, exactly the features the same
    # observation has without team-mates, in its order (sight_margin, a team-only feature, too).
    cls = OBSERVATIONS[name]
    extra = {"team_sight": True} if "team_sight" in inspect.signature(cls).parameters else {}
    team = cls(opponents=opponents, mates=mates, in_play=team_flags, **extra)
    lone = cls(opponents=opponents, mates=0, in_play=lone_flags, **extra)
    picked = team.lone_features(lone_flags)
    assert [team.features()[i] for i in picked] == lone.features()
    assert len(picked) == lone.dim < team.dim
    if extra:
        assert "sight_margin" in [f["name"] for f in team.features()]
    if not team_flags:
        with pytest.raises(ValueError, match="no in-play flags"):
            team.lone_features(True)


def test_a_lone_checkpoint_flies_each_seat_of_a_team(team_sets, tmp_path, tiny_run, lone_run):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from rlplat.agents.checkpoint import actor_from_state, load_checkpoint
    from rlplat.agents.export import observation_key
    from rlplat.experiment.evaluation import evaluate_run, load_run_config
    from rlplat.experiment.factory import build_env

    lone = lone_run
    state = load_checkpoint(Path(lone) / "checkpoints" / "best.pt")
    torch.manual_seed(0)  # a few updates leave the actor near its zero start: move it off
    state["actor"] = {k: v + torch.randn_like(v) for k, v in state["actor"].items()}
    env = build_env(load_run_config(lone), scenarios=team_sets[2, 1], split="val", num_envs=5)
    td = env.reset()
    features = env.obs_fn.lone_features()
    seats = actor_from_state(state, env.drone_action_spec, group=env.group, features=features)
    alone = actor_from_state(state, env.drone_action_spec)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        actions = seats(td.clone())[env.action_key]  # (5, 2, A)
        for seat in range(2):  # each seat: the lone network on its own view, team-mate unseen
            obs = td[observation_key(env.group)][:, seat, features]
            single = alone(TensorDict({"observation": obs}, [5]))["action"]
            assert torch.equal(actions[:, seat], single)
    assert not torch.equal(actions[:, 0], actions[:, 1])
    env.close()

    kwargs = dict(plots=False, split="val", scenarios_dir=team_sets[2, 1].path)
    ev = evaluate_run(lone, lone_in_team=True, out_dir=tmp_path / "team", **kwargs)
    assert ev.summary["attackers"] == 2 and ev.summary["lone_in_team"] is True
    assert "team_speed_ratio" in ev.rows[0]
    first = evaluate_run(lone, attackers=1, out_dir=tmp_path / "first", **kwargs)
    assert first.summary["lone_in_team"] is False
    no_team = r"^lone_in_team: .* flies attackers=1, no team \(scenarios_dir, attackers\)$"
    with pytest.raises(ConfigError, match=no_team):
        evaluate_run(lone, lone_in_team=True, attackers=1, out_dir=tmp_path / "x", **kwargs)
    with pytest.raises(ConfigError, match=r"^attackers: 3, the scenarios have 2 \(at most\)$"):
        evaluate_run(lone, attackers=3, out_dir=tmp_path / "y", **kwargs)

    # A lone defender in each seat of a pair (its observation has no in-play flags, the pair's has).
    guard = tiny_run(team_sets[1, 1], tmp_path / "d1", "drone=defender_v1")["run_dir"]
    kwargs["scenarios_dir"] = team_sets[1, 2].path
    pair = evaluate_run(guard, lone_in_team=True, out_dir=tmp_path / "pair", **kwargs).summary
    assert (pair["defenders"], pair["lone_in_team"]) == (2, True)
    # On a set of one defender there is no team of defenders; attackers= chooses none.
    kwargs["scenarios_dir"] = team_sets[2, 1].path
    no_team = r"^lone_in_team: .* flies defenders=1, no team \(scenarios_dir\)$"
    with pytest.raises(ConfigError, match=no_team):
        evaluate_run(guard, lone_in_team=True, out_dir=tmp_path / "z", **kwargs)


def test_an_artifact_flies_a_seat_on_the_lone_features():
    from rlplat.agents.native import artifact_module

    class Rows:  # a numpy policy as the C and ONNX runners are: rows in, rows out
        action_dim = 2

        def __call__(self, x):
            self.seen = x.copy()
            return x[:, :2] * 10

    runner = Rows()
    module = artifact_module(runner, ("attacker", "observation"), ("attacker", "action"), [4, 0, 2])
    obs = torch.arange(2 * 3 * 5, dtype=torch.float32).reshape(2, 3, 5)
    td = module(TensorDict({("attacker", "observation"): obs}, [2]))
    assert runner.seen.shape == (6, 3)
    assert torch.equal(td["attacker", "action"], obs[..., [4, 0]] * 10)


def test_a_team_trained_defender_network_is_refused_for_scripted_defenders(
    team_sets, tmp_path, tiny_run
):
    from rlplat.agents.policies import load_controller

    run = tiny_run(team_sets[1, 2], tmp_path / "run", "drone=defender_v1")["run_dir"]
    with pytest.raises(ConfigError, match=r"trained with 1 attackers and 2 defenders"):
        load_controller(f"{run}/checkpoints/best.pt", "defender", "env.defender_network")


def test_a_capture_pays_every_attacker_and_the_root_reward_is_the_team_mean(team_sets):
    env = make_env("drone=attacker_v4", scenarios=team_sets[2, 1], split="val", num_envs=16)
    env.set_seed(0)
    rollout = env.rollout(400, make_scripted_policy("pure_pursuit", env), break_when_any_done=False)
    nxt = rollout["next"]
    reward = nxt["attacker", "reward"].squeeze(-1)  # (N, T, 2)
    captured = nxt["captured"].squeeze(-1)
    assert captured.any()
    # Eq. 3 on a capture step is +10 for both, whichever attacker came close.
    assert (reward[captured] == 10.0).all()
    torch.testing.assert_close(nxt["reward"].squeeze(-1), reward.mean(-1))
    # Each attacker's distance is its own, to the defender.
    p = nxt["positions"]
    own = (p[..., 2:3, :] - p[..., :2, :]).norm(dim=-1)
    torch.testing.assert_close(nxt["attacker", "distance"].squeeze(-1), own)


def test_a_lone_checkpoint_starts_each_seat_of_a_team_run(
    team_sets, tmp_path, tiny, tiny_run, lone_run
):
    # init_from: a team run starts with the lone run's actor and critics in each seat; they
    # compute on the team's observations what they computed alone (team-mates weighted 0).
    from rlplat.agents.checkpoint import (
        actor_from_state,
        load_checkpoint,
        save_checkpoint,
        saved_net,
    )
    from rlplat.agents.export import observation_key
    from rlplat.agents.sac import make_critic, net_spec
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.factory import build_env
    from rlplat.experiment.training import make_agent, make_interface, warm_start, warm_start_state

    lone = lone_run
    state = load_checkpoint(Path(lone) / "checkpoints" / "best.pt")
    torch.manual_seed(0)  # a few updates leave the networks near their start: move them off
    loss, prefix = state["agent"]["loss"], "actor_network_params."
    moved = {k: v + torch.randn_like(v) for k, v in loss.items() if "network_params" in k}
    loss.update({k: v for k, v in moved.items() if not k.endswith("inv_scale")})
    learned = {k[len(prefix) :]: v for k, v in loss.items() if k.startswith(prefix)}
    # The actor it flies (the moving average of the default's) is not the one it learns.
    state["actor"] = {k: v + (0 if k.endswith("inv_scale") else torch.randn_like(v))
                      for k, v in learned.items()}  # fmt: skip
    save_checkpoint(tmp_path / "moved.pt", state)

    overrides = [*tiny, f"scenarios_dir={team_sets[2, 1].path}", f"init_from={tmp_path}/moved.pt"]
    cfg = compose_config("train", overrides)
    env = build_env(cfg, scenarios=team_sets[2, 1], split="val", num_envs=5)
    net = net_spec(env.obs_fn.scale, env.drone_action_spec.shape[-1], cfg.algo)
    td = env.reset()
    obs = td[observation_key(env.group)]  # (5, 2, D)
    features = env.obs_fn.lone_features()
    assert len(features) < obs.shape[-1]  # the team's observation holds more: its team-mate
    flies = actor_from_state(state, env.drone_action_spec)
    learns = actor_from_state({**state, "actor": learned}, env.drone_action_spec)

    def each_seat_flies(policy, alone):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            actions = policy(td.clone())[env.action_key]
            for seat in range(2):
                single = alone(TensorDict({"observation": obs[:, seat, features]}, [5]))
                torch.testing.assert_close(actions[:, seat], single["action"])
        assert not torch.equal(actions[:, 0], actions[:, 1])

    # Without a moving average the run's actor is the one the checkpoint flew.
    plain = compose_config("train", [*overrides, "algo.actor_average=0"])
    agent = make_agent(net, env, plain.algo, "cpu")
    warm_start(agent, *warm_start_state(plain), net, make_interface(plain, env), env)
    each_seat_flies(agent.policy, flies)
    # With one (the default's) it learns on from the checkpoint's actor and flies its average.
    agent = make_agent(net, env, cfg.algo, "cpu")
    assert agent.average_rate > 0
    warm_start(agent, *warm_start_state(cfg), net, make_interface(cfg, env), env)
    each_seat_flies(agent.flown_policy, flies)
    each_seat_flies(agent.policy, learns)
    action = torch.rand(5, 2, net.action_dim)
    for critics in ("qvalue_network_params", "target_qvalue_network_params"):
        for i in range(2):  # each of the two critics, and their targets
            critic, team_critic = make_critic(saved_net(state)), make_critic(net)
            for c, entries in ((critic, loss), (team_critic, agent.loss.state_dict())):
                c.module.load_state_dict(
                    {
                        k[len(critics) + len(".module.") :]: v[i]
                        for k, v in entries.items()
                        if k.startswith(critics + ".")
                    }  # fmt: skip
                )
            q_team = team_critic(TensorDict({"observation": obs, "action": action}, [5, 2]))
            q_lone = critic(
                TensorDict({"observation": obs[..., features], "action": action}, [5, 2])
            )
            torch.testing.assert_close(q_team["state_action_value"], q_lone["state_action_value"])
    assert agent.loss.log_alpha.item() == pytest.approx(loss["log_alpha"].item())
    env.close()

    # The run itself: it flies its own policy from the first frame and records where it started.
    summary = tiny_run(team_sets[2, 1], tmp_path / "2v1", f"init_from={lone}")
    assert summary["attackers"] == 2
    saved = load_checkpoint(Path(summary["run_dir"]) / "checkpoints" / "last.pt")
    assert saved["config"]["init_from"] == lone

    # What cannot start it: no file; a team's checkpoint for a lone run; another learner.
    with pytest.raises(ConfigError, match=r"^init_from: no checkpoint at .*nowhere"):
        tiny_run(team_sets[2, 1], tmp_path / "x", f"init_from={tmp_path}/nowhere")
    with pytest.raises(
        ConfigError, match=r"^init_from: .* trained with attackers=2, this run has attackers=1$"
    ):
        tiny_run(team_sets[1, 1], tmp_path / "y", f"init_from={summary['run_dir']}")
    with pytest.raises(ConfigError, match=r"^init_from: .* trained with drone.learner=attacker"):
        tiny_run(team_sets[1, 1], tmp_path / "z", "drone=defender_v1", f"init_from={lone}")


@pytest.mark.parametrize(
    ("team", "overrides", "learners"),
    [((2, 1), [], "2 attackers"), ((1, 2), ["drone=defender_v1"], "2 defenders")],
)
def test_self_imitation_of_a_team_of_learners_is_refused_before_any_work(
    team_sets, tmp_path, tiny_run, team, overrides, learners
):
    with pytest.raises(ConfigError, match=rf"^algo\.self_imitation: .* team of {learners} "):
        tiny_run(team_sets[team], tmp_path / "run", "algo.self_imitation=1e-4", *overrides)
    assert not (tmp_path / "run").exists()
    if team == (2, 1):  # the set flown by its first attacker alone is a lone learner: it trains
        tiny_run(team_sets[team], tmp_path / "one", "algo.self_imitation=1e-4", "env.attackers=1")
        assert (tmp_path / "one" / "checkpoints" / "best.pt").is_file()
        # critics that learn a shaped reward value other returns than the env's
        shaped = r"^algo\.self_imitation: 0\.0001 compares .*; set algo\.potential_weight=0$"
        with pytest.raises(ConfigError, match=shaped):
            tiny_run(team_sets[1, 1], tmp_path / "shaped", "algo.self_imitation=1e-4",
                     "algo.potential_weight=-5")  # fmt: skip
        assert not (tmp_path / "shaped").exists()
