"""A learned correction to proportional navigation, the observation with the drone's own speed,
and the capture ceiling of a split."""

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from rlplat import make_env
from rlplat.agents.policies import ProportionalNavigation, make_scripted_policy
from rlplat.envs.dynamics import VelocityDynamics
from rlplat.errors import ConfigError
from rlplat.eval.ceiling import intercept_ceiling
from rlplat.eval.episodes import evaluate
from rlplat.scenarios import STRATEGIES

GUIDED = "action=guided_velocity"
PLAIN = "drone=attacker_v3"  # eq. 1 and 2: the plain velocity action
V4 = "drone=attacker_v4"  # pursuit_state, a 3-d guided action, proportional navigation's start


@pytest.mark.parametrize("accel_lead", [0.0, 0.9])
def test_a_zero_correction_flies_proportional_navigation(scenarios, accel_lead):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    guided = make_env(
        PLAIN, GUIDED, f"action.accel_lead={accel_lead}", scenarios=scenarios, num_envs=n,
        split="val",
    )  # fmt: skip
    pn = make_scripted_policy("proportional_navigation", plain, accel_lead=accel_lead)
    a, b = plain.reset(), guided.reset()
    for _ in range(30):
        a = plain.step(pn(a))["next"]
        b = guided.step(b.set("action", torch.zeros(n, 3)))["next"]
        # The same arithmetic on the same state: bit-identical positions.
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=0)


def test_the_correction_moves_the_command_by_scale_times_the_action(scenarios):
    env = make_env(GUIDED, "action.scale=2", scenarios=scenarios, num_envs=4, split="val")
    td = env.reset()
    p, v = env.dynamics.position, env.dynamics.velocity
    guidance = env.guidance(p, v)[:, 0]  # (N, 3)
    action = torch.tensor([[0.1, -0.2, 0.0]]).expand(4, 3)
    speed = td["max_speed"][:, 0]
    command = env.action_fn(action.unsqueeze(1), speed.unsqueeze(1), guidance.unsqueeze(1))[:, 0]
    expected = (guidance + 2 * action).clamp(-1, 1) * speed.unsqueeze(-1)
    torch.testing.assert_close(command, expected)


def test_a_scripted_policy_flies_its_own_commands_through_a_guided_action(scenarios):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    guided = make_env(PLAIN, GUIDED, scenarios=scenarios, num_envs=n, split="val")
    pp_plain = make_scripted_policy("pure_pursuit", plain)
    pp_guided = make_scripted_policy("pure_pursuit", guided)
    a, b = plain.reset(), guided.reset()
    for _ in range(30):
        a = plain.step(pp_plain(a))["next"]
        b = guided.step(pp_guided(b))["next"]
    # The inverse is exact up to float rounding ((x - g) / 2 * 2 + g differs from x by an ulp),
    # which 30 steps of first-order dynamics do not amplify beyond micrometres.
    torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)


def test_a_guided_action_refuses_a_defender_learner(scenarios):
    with pytest.raises(ConfigError, match="guided action flies attackers"):
        make_env("drone=defender_v1", GUIDED, scenarios=scenarios)


def test_the_env_reports_each_drones_acceleration_over_the_last_control_period(scenarios):
    env = make_env(PLAIN, scenarios=scenarios, num_envs=4, split="val")
    td = env.reset()
    assert td["accelerations"].shape == (4, 2, 3) and not td["accelerations"].any()
    pn = make_scripted_policy("proportional_navigation", env)
    for _ in range(5):
        before = td["velocities"]
        td = env.step(pn(td))["next"]
        expected = (td["velocities"] - before) / env.control_period
        torch.testing.assert_close(td["accelerations"], expected)
    assert td["accelerations"].abs().amax() > 0.1  # both drones speed up from rest
    env.check_env_specs()


def test_the_augmented_law_aims_with_the_velocity_the_target_turns_to(scenarios):
    # The target flies 1 m/s along +y and accelerates at 2 m/s^2 along -y: under a 0.5-s
    # acceleration lead the law aims as at a target flying v + 0.5 a = 0 along y.
    own = ProportionalNavigation(gain=1.0, learner="attacker", attackers=1, defenders=1,
                                 team=False, accel_lead=0.5)  # fmt: skip
    assert own.in_keys[-1] == "accelerations"
    positions = torch.tensor([[[0.0, 0.0, 10.0], [10.0, 0.0, 10.0]]])
    velocities = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    accelerations = torch.tensor([[[0.0, 0.0, 0.0], [0.0, -2.0, 0.0]]])
    speeds, caught = torch.tensor([[5.0, 2.0]]), torch.zeros(1, 1, dtype=torch.bool)
    action = own(positions, velocities, speeds, caught, accelerations)
    torch.testing.assert_close(action, torch.tensor([[1.0, 0.0, 0.0]]))
    textbook = ProportionalNavigation(gain=1.0, learner="attacker", attackers=1, defenders=1,
                                      team=False)  # fmt: skip
    assert textbook(positions, velocities, speeds, caught)[0, 1] > 0  # leads along +y
    with pytest.raises(ValueError, match="accel_lead > 0 needs accelerations"):
        own(positions, velocities, speeds, caught)


def test_a_law_action_with_a_correction_adds_it_to_the_laws_command(scenarios):
    n = len(scenarios.split("val"))
    law = make_env(PLAIN, LAW, scenarios=scenarios, num_envs=n, split="val")
    corrected = make_env(PLAIN, LAW, "action.correction_reach=0.5", scenarios=scenarios,
                         num_envs=n, split="val")  # fmt: skip
    assert corrected.full_action_spec["action"].shape == (n, 6)
    assert not corrected.action_fn.invertible
    params = torch.tensor([0.3, -0.2, 0.5])
    a, b = law.reset(), corrected.reset()
    for _ in range(20):  # a zero correction flies the law its parameters set
        a = law.step(a.set("action", params.expand(n, 3)))["next"]
        b = corrected.step(b.set("action", torch.cat([params, torch.zeros(3)]).expand(n, 6)))
        b = b["next"]
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=0)
    # The correction moves the command by reach * c per axis, within the speed limit.
    fn, speed = corrected.action_fn, torch.tensor([4.0])
    guidance = fn.guidance(torch.tensor([[30.0, 0.0, 0.0]]), torch.zeros(1, 3), speed)
    c = torch.tensor([[0.0, 0.0, 0.0, -1.0, 0.4, 0.0]])
    torch.testing.assert_close(fn(c, speed, guidance), torch.tensor([[2.0, 0.8, 0.0]]))
    with pytest.raises(ConfigError, match="action.correction_reach >= 2"):
        make_scripted_policy("pure_pursuit", corrected)


@pytest.mark.parametrize("accel_reach", [0.0, 0.5])
def test_the_card_names_every_component_of_a_corrected_law_action(scenarios, accel_reach):
    env = make_env(LAW, f"action.accel_reach={accel_reach}", "action.correction_reach=0.5",
                   scenarios=scenarios, num_envs=2)  # fmt: skip
    card = env.action_fn.card()
    assert len(card["features"]) == env.action_fn.dim == (7 if accel_reach else 6)
    assert card["features"][-3:] == ["correction.x", "correction.y", "correction.z"]
    assert "clamp(pn + 0.5 * (a" in card["unit"] and card["guidance"]["correction_reach"] == 0.5


def test_a_correction_of_reach_two_flies_every_scripted_policy(scenarios):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    corrected = make_env(PLAIN, LAW, "action.correction_reach=2", scenarios=scenarios,
                         num_envs=n, split="val")  # fmt: skip
    for name in ("pure_pursuit", "proportional_navigation"):
        a, b = plain.reset(), corrected.reset()
        on_plain = make_scripted_policy(name, plain)
        through = make_scripted_policy(name, corrected)
        for _ in range(30):
            a = plain.step(on_plain(a))["next"]
            b = through(b)
            assert (b["action"][:, :3] == 0).all()  # the law at its zero action, corrected
            b = corrected.step(b)["next"]
            torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.schema import validate_train_config

    # attacker_v4's scripted start (proportional navigation plus noise) flies through it.
    validate_train_config(compose_config("train", [V4, LAW, "action.correction_reach=2"]))
    with pytest.raises(ConfigError, match="algo.init_policy: 'proportional_navigation' cannot"):
        validate_train_config(compose_config("train", [V4, LAW, "action.correction_reach=1.5"]))


@pytest.mark.parametrize(
    "key,value", [("scale", 0), ("lead", -1), ("gain", -2), ("accel_lead", -0.5)]
)
def test_a_guided_action_refuses_bad_knobs(scenarios, key, value):
    with pytest.raises(ConfigError, match=f"action.{key}"):
        make_env(GUIDED, f"action.{key}={value}", scenarios=scenarios)


LAW = "action=guidance_law"


@pytest.mark.parametrize(
    "action,law",
    [
        ((0.0, 0.0, 0.0), {}),  # the zero action: the configured law itself
        ((0.0, -1.0, 0.0), {"lead": 0.0}),  # no lead: pure pursuit's command
        ((1.0, 0.5, -1.0), {"gain": 25.0, "lead": 0.75, "max_lead_time": 1.0}),
        ((-1.0, 1.0, 1.0), {"gain": 1.0, "lead": 1.0, "max_lead_time": 16.0}),
    ],
)
def test_a_law_action_flies_the_law_it_sets(scenarios, action, law):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    learned = make_env(PLAIN, LAW, scenarios=scenarios, num_envs=n, split="val")
    pn = make_scripted_policy("proportional_navigation", plain, **law)
    a, b = plain.reset(), learned.reset()
    for _ in range(30):
        a = plain.step(pn(a))["next"]
        b = learned.step(b.set("action", torch.tensor(action).expand(n, 3)))["next"]
        # gain * f ** a is rounded once more than the plain law's gain (an ulp at most)
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)


def test_an_augmented_law_action_flies_the_augmented_law(scenarios):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    learned = make_env(PLAIN, LAW, "action.accel_lead=0.9", scenarios=scenarios, num_envs=n,
                       split="val")  # fmt: skip
    pn = make_scripted_policy("proportional_navigation", plain, accel_lead=0.9, lead=0.75)
    a, b = plain.reset(), learned.reset()
    for _ in range(30):
        a = plain.step(pn(a))["next"]
        b = learned.step(b.set("action", torch.tensor([0.0, 0.5, 0.0]).expand(n, 3)))["next"]
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)
    textbook = make_env(PLAIN, LAW, scenarios=scenarios, num_envs=n, split="val")
    c = textbook.reset()
    for _ in range(30):
        c = textbook.step(c.set("action", torch.tensor([0.0, 0.5, 0.0]).expand(n, 3)))["next"]
    assert (c["positions"] - b["positions"]).abs().amax() > 0.01  # the term changes the flight


@pytest.mark.parametrize("a3,accel_lead", [(-1.0, 0.0), (0.0, 0.9), (0.5, 1.35)])
def test_a_fourth_component_sets_the_acceleration_lead(scenarios, a3, accel_lead):
    n = len(scenarios.split("val"))
    plain = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="val")
    learned = make_env(PLAIN, LAW, "action.accel_lead=0.9", "action.accel_reach=0.9",
                       scenarios=scenarios, num_envs=n, split="val")  # fmt: skip
    assert learned.full_action_spec["action"].shape == (n, 4)
    pn = make_scripted_policy("proportional_navigation", plain, accel_lead=accel_lead)
    a, b = plain.reset(), learned.reset()
    for _ in range(30):
        a = plain.step(pn(a))["next"]
        b = learned.step(b.set("action", torch.tensor([0.0, 0.0, 0.0, a3]).expand(n, 4)))["next"]
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)


def test_a_team_flies_the_augmented_law_at_each_attackers_nearest_defender(
    tmp_path, write_small_set
):
    teams = write_small_set(tmp_path / "2v2", "scenario.attackers=2", "scenario.defenders=2")
    n = len(teams.split("val"))
    plain = make_env(PLAIN, scenarios=teams, num_envs=n, split="val")
    learned = make_env(PLAIN, LAW, "action.accel_lead=0.9", scenarios=teams, num_envs=n,
                       split="val")  # fmt: skip
    pn = make_scripted_policy("proportional_navigation", plain, accel_lead=0.9)
    a, b = plain.reset(), learned.reset()
    textbook = make_env(PLAIN, LAW, scenarios=teams, num_envs=n, split="val")
    c, zero = textbook.reset(), torch.zeros(n, 2, 3)
    for _ in range(30):
        a = plain.step(pn(a))["next"]
        b = learned.step(b.set(learned.action_key, zero))["next"]
        c = textbook.step(c.set(textbook.action_key, zero))["next"]
        torch.testing.assert_close(a["positions"], b["positions"], rtol=0, atol=1e-4)
    assert (c["positions"] - b["positions"]).abs().amax() > 0.01  # the term changes the flight


def test_a_law_action_flies_no_scripted_policy(scenarios):
    env = make_env(PLAIN, LAW, scenarios=scenarios, num_envs=4, split="val")
    with pytest.raises(ConfigError, match="pure_pursuit cannot be flown through action=guidance"):
        make_scripted_policy("pure_pursuit", env)
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.schema import validate_train_config

    validate_train_config(compose_config("train", [V4, LAW, "algo.init_policy=random"]))
    with pytest.raises(ConfigError, match="algo.init_policy: 'proportional_navigation' cannot"):
        validate_train_config(compose_config("train", [V4, LAW]))  # attacker_v4's scripted start


@pytest.mark.parametrize(
    "key,value",
    [("gain_factor", 1), ("lead_reach", -0.1), ("accel_reach", -0.1), ("correction_reach", -0.1)],
)
def test_a_law_action_refuses_bad_knobs(scenarios, key, value):
    with pytest.raises(ConfigError, match=f"action.{key}"):
        make_env(LAW, f"action.{key}={value}", scenarios=scenarios)


def test_pursuit_state_adds_the_own_maximum_speed(scenarios):
    env = make_env(PLAIN, "observation=pursuit_state", scenarios=scenarios, num_envs=5, split="val")
    td = env.reset()
    obs = td["observation"]
    assert obs.shape == (5, 10)
    names = [f["name"] for f in env.obs_fn.features()]
    assert names[3] == "max_speed_own" and env.obs_fn.features()[3]["unit"] == "m/s"
    torch.testing.assert_close(obs[:, 3], td["max_speed"][:, 0])
    base = make_env(PLAIN, scenarios=scenarios, num_envs=5, split="val").reset()["observation"]
    torch.testing.assert_close(obs[:, [0, 1, 2, 4, 5, 6, 7, 8, 9]], base)


def test_pursuit_clock_adds_the_time_left_until_the_time_limit(scenarios):
    env = make_env(V4, "observation=pursuit_clock", "env.time_limit=2", scenarios=scenarios,
                   num_envs=5, split="val")  # fmt: skip
    td = env.reset()
    assert td["observation"].shape == (5, 11)
    feature = env.obs_fn.features()[4]
    assert feature == {"name": "time_left", "unit": "s", "scale": 60.0}
    left = [td["observation"][:, 4]]
    for _ in range(20):  # 2 s of 0.1-s steps: the last one truncates every episode
        td = env.step(td.set("action", torch.zeros(5, 3)))["next"]
        left.append(td["observation"][:, 4])
    expected = torch.linspace(2.0, 0.0, 21).unsqueeze(1).expand(21, 5)
    torch.testing.assert_close(torch.stack(left), expected)
    assert td["done"].all()
    state = make_env(V4, "observation=pursuit_state", scenarios=scenarios, num_envs=5, split="val")
    first = make_env(V4, "observation=pursuit_clock", scenarios=scenarios, num_envs=5, split="val")
    torch.testing.assert_close(
        first.reset()["observation"][:, [0, 1, 2, 3, *range(5, 11)]], state.reset()["observation"]
    )


def test_pursuit_accel_adds_the_opponents_acceleration_the_env_reports(scenarios):
    env = make_env(V4, "observation=pursuit_accel", scenarios=scenarios, num_envs=5, split="val")
    state = make_env(V4, "observation=pursuit_state", scenarios=scenarios, num_envs=5, split="val")
    td, base = env.reset(), state.reset()
    assert td["observation"].shape == (5, 13)
    names = [f["name"] for f in env.obs_fn.features()[10:]]
    assert names == ["a_opponent0.x", "a_opponent0.y", "a_opponent0.z"]
    assert env.obs_fn.features()[10]["unit"] == "m/s^2"
    torch.testing.assert_close(td["observation"][:, 10:], torch.zeros(5, 3))  # at rest
    for _ in range(15):
        td = env.step(td.set("action", torch.ones(5, 3)))["next"]
        base = state.step(base.set("action", torch.ones(5, 3)))["next"]
        # The same flight: the first ten features are pursuit_state's, the last three the
        # defender's acceleration as the env reports it.
        torch.testing.assert_close(td["observation"][:, :10], base["observation"])
        torch.testing.assert_close(td["observation"][:, 10:], td["accelerations"][:, 1])
    assert td["observation"][:, 10:].abs().amax() > 0.1  # the defenders turn and speed up
    check_env_specs(env)


def test_pursuit_world_adds_where_the_drone_is_on_the_map(scenarios):
    env = make_env(V4, "observation=pursuit_world", scenarios=scenarios, num_envs=5, split="val")
    state = make_env(V4, "observation=pursuit_state", scenarios=scenarios, num_envs=5, split="val")
    td, base = env.reset(), state.reset()
    assert td["observation"].shape == (5, 13)
    features = env.obs_fn.features()
    assert [f["name"] for f in features[4:7]] == ["p_own.x", "p_own.y", "p_own.z"]
    assert {f["unit"] for f in features[4:7]} == {"m"}
    assert [f["scale"] for f in features[4:7]] == [50.0] * 3  # world_scale, not position_scale
    for _ in range(15):
        # The same flight: pursuit_state's features around the attacker's world position.
        torch.testing.assert_close(td["observation"][:, [0, 1, 2, 3, *range(7, 13)]],
                                   base["observation"])  # fmt: skip
        torch.testing.assert_close(td["observation"][:, 4:7], td["positions"][:, 0])
        td = env.step(td.set("action", torch.ones(5, 3)))["next"]
        base = state.step(base.set("action", torch.ones(5, 3)))["next"]
    check_env_specs(env)


def test_pursuit_route_adds_the_defenders_next_two_setpoints(scenarios):
    env = make_env(V4, "observation=pursuit_route", scenarios=scenarios, num_envs=5, split="val")
    state = make_env(V4, "observation=pursuit_state", scenarios=scenarios, num_envs=5, split="val")
    td, base = env.reset(), state.reset()
    assert td["observation"].shape == (5, 16)
    names = [f["name"] for f in env.obs_fn.features()[4:10]]
    assert names[0] == "(setpoint - p_own).x" and names[3] == "(next_setpoint - p_own).x"
    moved_on = 0
    for _ in range(120):
        obs, own = td["observation"], td["positions"][:, 0]
        torch.testing.assert_close(obs[:, [0, 1, 2, 3, *range(10, 16)]], base["observation"])
        torch.testing.assert_close(obs[:, 4:7], td["setpoints"][:, 0] - own)
        ahead, waypoint = obs[:, 7:10] + own, td["waypoint"][:, 0]
        td = env.step(td.set("action", torch.ones(5, 3)))["next"]
        base = state.step(base.set("action", torch.ones(5, 3)))["next"]
        # A defender that reached its setpoint flies to the one the attacker saw next.
        on = td["waypoint"][:, 0] > waypoint
        torch.testing.assert_close(td["setpoints"][on, 0], ahead[on])
        moved_on += int(on.sum())
        if td["done"].any():
            break
    assert moved_on >= 2  # the check above was made
    check_env_specs(env)


# The capture ceiling --------------------------------------------------------------------


def _ceiling(env, dynamics_cfg=None):
    n = env.batch_size[0]
    dynamics = VelocityDynamics(num_envs=n, num_drones=2, device="cpu", **(dynamics_cfg or {}))
    return intercept_ceiling(env, dynamics)


def test_no_policy_captures_where_the_ceiling_says_no_intercept_exists(tmp_path, write_small_set):
    scenarios = write_small_set(tmp_path, "scenario.n_test=96")
    n = len(scenarios.split("test"))
    env = make_env(PLAIN, scenarios=scenarios, num_envs=n, split="test")
    ceiling = _ceiling(env)
    setpoints = env.scenarios["defender_strategy"][:, 0] == STRATEGIES.index("setpoints")
    assert torch.equal(ceiling.defined, setpoints)  # route-flying defenders only
    assert 0 < ceiling.rate <= 1
    for name in ("pure_pursuit", "proportional_navigation"):
        flown = evaluate(env, make_scripted_policy(name, env))
        impossible = setpoints & (ceiling.interceptable == 0)
        assert not (flown.captured & impossible).any(), name
        # where it captured, the bound's earliest intercept is no later than the capture
        caught = flown.captured & setpoints
        assert (ceiling.earliest[caught] <= flown.time_to_capture[caught] + 1e-4).all(), name


def test_a_slow_attacker_cannot_catch_a_fast_defender_flying_away(tmp_path, write_small_set):
    # Every defender flies its route at 4.5-5 m/s per axis, every attacker at 1-1.5 m/s and
    # starts far away: hardly any intercept exists; with the attackers as fast, most do.
    slow = write_small_set(
        tmp_path / "slow",
        "scenario.params.attacker_max_speed.high=1.5",
        "scenario.params.defender_max_speed.low=4.5",
        "scenario.strategy_mix={setpoints: 1, nn: 0}",
    )
    fast = write_small_set(
        tmp_path / "fast",
        "scenario.params.attacker_max_speed.low=4.5",
        "scenario.params.defender_max_speed.high=1.5",
        "scenario.strategy_mix={setpoints: 1, nn: 0}",
    )
    rates = {}
    for name, s in (("slow", slow), ("fast", fast)):
        n = len(s.split("test"))
        rates[name] = _ceiling(make_env(PLAIN, scenarios=s, num_envs=n, split="test")).rate
    assert rates["slow"] < 0.5 < rates["fast"] == 1.0


def test_the_route_ceiling_flies_every_defender_on_its_route(tmp_path, write_small_set):
    from rlplat.eval.ceiling import route_flown

    scenarios = write_small_set(tmp_path, "scenario.n_test=96")
    flown = route_flown(scenarios)
    strategy = scenarios.split("test")["defender_strategy"]
    nn = strategy[:, 0] == STRATEGIES.index("nn")
    assert nn.any() and (~nn).any()  # the set itself is untouched: both strategies
    assert (flown.split("test")["defender_strategy"] == STRATEGIES.index("setpoints")).all()
    for key in ("attacker_start", "defender_start", "route", "defender_max_speed"):
        assert torch.equal(flown.split("test")[key], scenarios.split("test")[key]), key
    n = len(strategy)
    ceiling = _ceiling(make_env(PLAIN, scenarios=scenarios, num_envs=n, split="test"))
    route = _ceiling(make_env(PLAIN, scenarios=flown, num_envs=n, split="test"))
    assert route.defined.all()
    # A route flyer's path is the same in both sets, so is its bound.
    torch.testing.assert_close(route.interceptable[~nn], ceiling.interceptable[~nn])
    assert ceiling.interceptable[nn].isnan().all()


# Where learning starts --------------------------------------------------------------------


def test_a_held_actor_keeps_its_policy_while_the_critics_learn(scenarios):
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from rlplat.agents.sac import net_spec
    from rlplat.agents.transitions import TRANSITION_KEYS
    from rlplat.experiment.config import compose_config
    from rlplat.experiment.training import held_actor, make_agent

    cfg = compose_config("train", [V4, "algo.compile=false", "algo.batch_size=32"])
    env = make_env(V4, scenarios=scenarios, num_envs=8)  # a 3-d correction
    agent = make_agent(net_spec(env.obs_fn.scale, 3, cfg.algo), env, cfg.algo, "cpu")
    loc_rows = agent.actor.module[0].module[0].body[-1].weight[:3]
    assert loc_rows.abs().max() == 0  # actor_zero_mean: a zero correction, proportional nav.
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(256), batch_size=32)
    td = env.reset()
    while len(buffer) < 256:
        td, nxt = env.step_and_maybe_reset(td.set("action", env.action_spec.rand()))
        buffer.extend(td.select(*TRANSITION_KEYS).clone())
        td = nxt
    actor = [p.detach().clone() for p in agent.loss.actor_network_params.values(True, True)]
    critic = [p.detach().clone() for p in agent.loss.qvalue_network_params.values(True, True)]
    for _ in range(3):
        with held_actor(agent, True):
            agent.update(buffer.sample())
    after = list(agent.loss.actor_network_params.values(True, True))
    assert all(torch.equal(a, b) for a, b in zip(actor, after, strict=True))
    moved = list(agent.loss.qvalue_network_params.values(True, True))
    assert not all(torch.equal(a, b) for a, b in zip(critic, moved, strict=True))
    with held_actor(agent, False):  # released: the actor learns
        agent.update(buffer.sample())
    released = list(agent.loss.actor_network_params.values(True, True))
    assert not all(torch.equal(a, b) for a, b in zip(actor, released, strict=True))
