import itertools
import re
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from rlplat import make_env
from rlplat.envs.components import (
    ACTIONS,
    OBSERVATIONS,
    REWARD_TERMS,
    Reward,
    RewardContext,
    inside_ellipsoid,
)
from rlplat.envs.kinematics import follow_route
from rlplat.envs.pursuit import PursuitEnv, _closest_approach
from rlplat.errors import ConfigError
from rlplat.experiment.config import compose_config

CONF = Path(__file__).resolve().parent.parent / "conf"


def stems(group: str) -> set[str]:
    return {p.stem for p in (CONF / group).glob("*.yaml")}


def _pursue(observation: torch.Tensor) -> torch.Tensor:
    """Fly at the defender with full speed (reads p_d - p_a from the eq. 1 observation)."""
    return (observation[..., 3:6] * 5).clamp(-1, 1)


pursue = TensorDictModule(_pursue, in_keys=["observation"], out_keys=["action"])


# Registries match conf/ ------------------------------------------------------------------


def test_registries_match_config_groups():
    assert (
        set(OBSERVATIONS)
        == {OmegaConf.load(CONF / "observation" / f"{s}.yaml").name for s in stems("observation")}
        == stems("observation")
    )
    # An action file is a registry entry or derives from one through its defaults list (e.g.
    # corrected_law: guidance_law with a correction; route_law_gated: route_law_held with a
    # gate, itself route_law with other times): its composed name is a registry key,
    # and every registry key has a file of its own name.
    names = {s: compose_config("train", [f"action={s}"]).action.name for s in stems("action")}
    assert set(names.values()) == set(ACTIONS) <= stems("action")
    assert all(names[key] == key for key in ACTIONS)
    for stem in stems("action") - set(ACTIONS):
        base = stem  # follow the first defaults entry down to the registry entry's file
        while base not in ACTIONS:
            raw = OmegaConf.load(CONF / "action" / f"{base}.yaml")
            assert "name" not in raw and raw.defaults[0] in stems("action"), base
            base = raw.defaults[0]
        assert base == names[stem], stem
    for s in stems("reward"):  # composed: a reward file may derive from another
        cfg = compose_config("train", [f"reward={s}"]).reward
        Reward(**cfg)  # every term known, every key a constructor argument
        assert set(cfg.terms) <= set(REWARD_TERMS)
    assert stems("drone") == {
        "attacker_v1",
        "attacker_v2",
        "attacker_v3",
        "attacker_v4",
        "attacker_v5",
        "attacker_v6",
        "attacker_v7",
        "attacker_v8",
        "attacker_v9",
        "attacker_v10",
        "attacker_v11",
        "attacker_v12",
        "attacker_v13",
        "attacker_v14",
        "defender_v1",
    }


def test_a_vision_ellipsoid_set_apart_from_the_sets_is_a_warning(scenarios, caplog):
    drawn = list(scenarios.spec.vision_semi_axes)
    with caplog.at_level("WARNING", logger="rlplat.experiment.factory"):
        make_env(scenarios=scenarios.path)  # the set's own: nothing to say
        assert "env.vision_semi_axes" not in caplog.text
        env = make_env("env.vision_semi_axes=[20,20,8]", scenarios=scenarios.path)
    assert (
        f"env.vision_semi_axes: the env sees within [20, 20, 8] m, the set's starts were drawn "
        f"within {drawn} m" in caplog.text
    )
    assert env.semi_axes.tolist() == [20, 20, 8]


@pytest.mark.parametrize(
    ("drone", "dim"),
    [
        ("attacker_v1", 12),
        ("attacker_v2", 3),
        ("attacker_v3", 9),
        ("attacker_v4", 10),
        ("attacker_v5", 10),
        ("attacker_v6", 10),
        ("attacker_v8", 10),
        ("attacker_v9", 16),
        ("attacker_v10", 20),
        ("attacker_v11", 24),
        ("attacker_v12", 24),
        ("attacker_v13", 24),
        ("attacker_v14", 24),
    ],
)
def test_drone_bundles_pick_their_observation_and_cli_wins(scenarios, drone, dim):
    env = make_env(f"drone={drone}", scenarios=scenarios.path, num_envs=2)
    assert env.observation_spec["observation"].shape == (2, dim)
    shaped = set(OmegaConf.load(CONF / "reward" / "shaped.yaml").terms)
    # attacker_v11 on put a price on the correction
    extra = {"action_sq"} if drone in ("attacker_v11", "attacker_v12") else set()
    assert set(env.reward_fn.weights) == shaped | extra  # eq. 3's terms by default
    env = make_env(f"drone={drone}", "reward=sparse", scenarios=scenarios.path)
    assert set(env.reward_fn.weights) == {"capture", "out_of_view", "ground_contact"}


# Specs for every combination -------------------------------------------------------------


def _rewards_of(drone: str) -> list[str]:
    """The rewards of the drone's side: an attacker's eq. 3 and sparse, a defender's evasion."""
    learner = OmegaConf.load(CONF / "drone" / f"{drone}.yaml").drone.get("learner", "attacker")
    return ["evasion"] if learner == "defender" else ["shaped", "sparse"]


@pytest.mark.parametrize(
    ("drone", "dynamics", "reward"),
    [
        (drone, dynamics, reward)
        for drone, dynamics in itertools.product(
            sorted(stems("drone")),
            sorted(set(stems("dynamics")) - {"airsim"}),  # a simulator: test_airsim_env.py
        )
        for reward in _rewards_of(drone)
    ],
)
def test_check_env_specs(scenarios, drone, dynamics, reward):
    env = make_env(
        f"drone={drone}",
        f"dynamics={dynamics}",
        f"reward={reward}",
        scenarios=scenarios,
        num_envs=3,
    )
    check_env_specs(env, seed=0)


# Reward, visibility, capture -------------------------------------------------------------


def test_shaped_reward_is_paper_eq3():
    cfg = OmegaConf.load(CONF / "reward" / "shaped.yaml")
    reward = Reward(**cfg)
    d = torch.tensor([1.0, 30.0, 60.0, 10.0, 0.0, 30.0])
    visible = torch.tensor([True, True, True, False, True, True])
    captured = torch.tensor([True, False, False, False, False, False])
    # Eq. 3 is the in-flight reward; the last case ends on the ground, which eq. 3 does not price.
    grounded = torch.tensor([False, False, False, False, False, True])
    total, terms = reward(RewardContext(d, visible, captured, grounded, 60.0))
    crash = cfg.terms.ground_contact
    eq3 = [10.0, -2 * 30**2 / 60**2 - 0.1, -2.0 - 0.1, -1.0, -0.1, -2 * 30**2 / 60**2 - 0.1]
    expected = eq3[:-1] + [eq3[-1] + crash]
    assert crash <= -1.0 / (1.0 - 0.99)  # a crash is never cheaper than staying out of view
    assert total.tolist() == pytest.approx(expected)
    assert sum(terms.values()).tolist() == pytest.approx(expected)
    sparse_cfg = OmegaConf.load(CONF / "reward" / "sparse.yaml")
    total, _ = Reward(**sparse_cfg)(RewardContext(d, visible, captured, grounded, 60.0))
    expected = [10.0, 0.0, 0.0, -1.0, 0.0, sparse_cfg.terms.ground_contact]
    assert total.tolist() == pytest.approx(expected)


def test_action_sq_prices_the_size_of_the_action(scenarios):
    env = make_env("drone=attacker_v10", "+reward.terms.action_sq=-0.5", scenarios=scenarios.path,
                   num_envs=3)  # fmt: skip
    td = env.reset()
    action = torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0], [0.6, 0.0, -0.3]])
    out = env.step(td.set("action", action))["next"]
    expected = -0.5 * torch.tensor([0.0, 1.0, (0.36 + 0.09) / 3]).unsqueeze(-1)
    torch.testing.assert_close(out["reward_terms", "action_sq"], expected)
    terms = sum(out["reward_terms", k] for k in env.reward_fn.weights)
    torch.testing.assert_close(out["reward"], terms)


def test_a_baseline_flies_without_the_price_of_a_correction():
    from rlplat.experiment.evaluation import plain_action

    cfg = compose_config("train", ["drone=attacker_v11"])
    plain = plain_action(cfg)
    assert plain.action.name == "velocity" and cfg.action.name == "route_law"
    assert set(plain.reward.terms) == set(cfg.reward.terms) - {"action_sq"}
    assert "action_sq" in cfg.reward.terms  # the run's own config is unchanged


def test_shaped_strict_makes_losing_sight_the_worst_in_flight_step():
    strict = OmegaConf.load(CONF / "reward" / "shaped_strict.yaml")
    eq3 = OmegaConf.load(CONF / "reward" / "shaped.yaml")
    axes = OmegaConf.load(CONF / "scenario" / "pursuit.yaml").vision_semi_axes
    d = torch.linspace(0.0, max(axes), 200)  # every in-view distance, the far edge included
    flags = torch.zeros(200, dtype=torch.bool)

    def step(cfg, visible):
        ctx = RewardContext(d, flags | visible, flags, flags, cfg.distance_scale)
        return Reward(**cfg)(ctx)[0]

    assert (step(strict, False) < step(strict, True)).all()
    assert (step(eq3, False) > step(eq3, True)).any()  # eq. 3: out of sight beats the far edge
    # Same in view as eq. 3; a crash still costs the worst step over the discounted horizon.
    torch.testing.assert_close(step(strict, True), step(eq3, True))
    assert strict.terms.ground_contact <= strict.terms.out_of_view / (1.0 - 0.99)


@pytest.mark.parametrize("drone", ["attacker_v6", "attacker_v13"])
def test_a_late_capture_pays_and_a_crash_never_does_under_the_bundles_discount(drone):
    cfg = compose_config("train", [f"drone={drone}"])
    eq3 = OmegaConf.load(CONF / "reward" / "shaped.yaml").terms
    terms, gamma = cfg.reward.terms, cfg.algo.gamma
    # In flight it pays eq. 3's terms; only the capture and the crash are scaled.
    assert {k: terms[k] for k in eq3 if k not in ("capture", "ground_contact")} == {
        k: v for k, v in eq3.items() if k not in ("capture", "ground_contact")
    }
    horizon = 1.0 / (1.0 - gamma)
    # A crash costs more than losing sight for the whole discounted horizon.
    assert terms.ground_contact <= terms.out_of_view * horizon
    # A capture 20 s ahead outweighs 20 s of in-view steps at 10 m, which eq. 3's capture
    # does not under the same discount.
    steps = round(20.0 / cfg.env.control_period)
    in_view = terms.in_view_step + terms.distance_sq * (10.0 / cfg.reward.distance_scale) ** 2
    chase = -in_view * (1.0 - gamma**steps) / (1.0 - gamma)
    assert terms.capture * gamma**steps > chase > eq3.capture * gamma**steps


def test_unknown_reward_term_lists_valid_ones():
    with pytest.raises(
        ConfigError, match=r"reward.terms.speed: unknown reward term; valid: capture"
    ):
        Reward(terms={"speed": 1.0})


def test_vision_ellipsoid_boundary():
    axes = torch.tensor([48.0, 42.0, 13.0])
    rel = torch.tensor(
        [
            [48.0, 0, 0],
            [48.01, 0, 0],
            [-48.0, 0, 0],
            [0, 42.0, 0],
            [0, -42.01, 0],
            [0, 0, 13.0],
            [0, 0, 13.01],
            [48 / 2**0.5, 42 / 2**0.5 - 0.01, 0],
            [48 / 2**0.5, 42 / 2**0.5 + 0.01, 0],
        ]
    )
    expected = [True, False, True, True, False, True, False, True, False]
    assert inside_ellipsoid(rel, axes).tolist() == expected


def test_capture_threshold_uses_closest_approach():
    before = torch.tensor([[1.19, 0, 0], [1.21, 0, 0], [5.0, 1.0, 0], [5.0, 1.3, 0]])
    after = torch.tensor([[1.19, 0, 0], [1.21, 0, 0], [-5.0, 1.0, 0], [-5.0, 1.3, 0]])
    closest = _closest_approach(before, after)
    assert closest.tolist() == pytest.approx([1.19, 1.21, 1.0, 1.3])
    assert (closest <= 1.2).tolist() == [True, False, True, False]


def test_capture_terminates_with_reward_and_true_final_observation(scenarios):
    env = make_env("drone=attacker_v3", scenarios=scenarios, num_envs=16)  # eq. 1 and 2
    env.set_seed(0)
    td = env.rollout(900, pursue, break_when_any_done=False)
    nxt = td["next"]
    cap = nxt["captured"].squeeze(-1)
    assert cap.any(), "pure pursuit with full speed should capture some defenders"
    assert nxt["terminated"][cap].all() and (nxt["reward"][cap] == 10.0).all()
    assert (nxt["distance"][cap] < 1.2 + 1.0).all()
    # The done step's observation is the final one, not the next episode's first.
    final = nxt["positions"][cap]
    assert torch.allclose(
        nxt["distance"][cap].squeeze(-1), (final[:, 1] - final[:, 0]).norm(dim=-1)
    )
    assert torch.allclose(nxt["observation"][cap][:, 3:6], final[:, 1] - final[:, 0], atol=1e-5)
    # Episode sums of the terms add up to the returns.
    terms = sum(nxt["reward_terms", k] for k in env.reward_fn.weights)
    assert torch.allclose(terms, nxt["reward"])


# Episodes, resets, seeding ---------------------------------------------------------------


def test_partial_reset_only_touches_flagged_envs(scenarios):
    env = make_env("drone=attacker_v4", scenarios=scenarios, num_envs=4)  # a 3-d action
    td = env.reset()
    assert td["scenario_index"].squeeze(-1).tolist() == [0, 1, 2, 3]  # sequential walk
    for _ in range(5):
        td = env.step(pursue(td))["next"].exclude("reward", "done", "terminated", "truncated")
    before = env.dynamics.position.clone()
    mask = torch.tensor([[True], [False], [True], [False]])
    out = env.reset(td.clone().set("_reset", mask))  # non-reset envs keep their entries
    assert out["scenario_index"].squeeze(-1).tolist() == [4, 1, 5, 3]
    assert env.step_count.tolist() == [0, 5, 0, 5]
    assert torch.equal(env.dynamics.position[[1, 3]], before[[1, 3]])
    starts = scenarios.split("train")[[4, 5]]
    assert torch.allclose(env.dynamics.position[[0, 2], :1], starts["attacker_start"])
    assert torch.allclose(env.dynamics.position[[0, 2], 1:], starts["defender_start"])
    assert not out["done"].any()


@pytest.mark.parametrize("order", ["shuffled", "random"])
def test_same_seed_same_rollout(scenarios, order):
    def run(seed):
        env = make_env(
            f"env.scenario_order={order}", "env.time_limit=3", scenarios=scenarios, num_envs=8
        )
        env.set_seed(seed)
        torch.manual_seed(0)  # random actions come from torch's global generator
        return env.rollout(100, break_when_any_done=False)

    a, b, c = run(1), run(1), run(2)
    assert (a == b).all()
    assert not torch.equal(a["scenario_index"], c["scenario_index"])


def test_weighted_draws_fly_the_weighted_scenarios_in_proportion(scenarios):
    env = make_env("env.time_limit=1", scenarios=scenarios, num_envs=64)
    n = len(env.scenarios)
    weights = torch.zeros(n)
    weights[:2] = torch.tensor([1.0, 3.0])  # only scenarios 0 and 1, one in four the first
    env.sampler.set_weights(weights)
    env.set_seed(0)
    drawn = torch.cat([env.reset()["scenario_index"].flatten() for _ in range(16)])
    assert set(drawn.tolist()) == {0, 1}
    assert (drawn == 0).float().mean().item() == pytest.approx(0.25, abs=0.05)  # 1024 draws
    env.set_seed(0)
    again = torch.cat([env.reset()["scenario_index"].flatten() for _ in range(16)])
    assert torch.equal(drawn, again)  # the walk's seed fixes the draws
    env.sampler.set_weights(None)  # the configured order again
    assert env.reset()["scenario_index"].flatten().tolist() == list(range(64))
    with pytest.raises(ValueError, match="scenario weights"):
        env.sampler.set_weights(-torch.ones(n))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("nn_weight", "team", "steps", "atol"),
    # Fused kernels round differently. The network-flown defenders (half the default set) feed
    # that back through the closed loop and the last bits grow about 10x every 20 steps, so
    # with them the rollouts are held together over a shorter horizon.
    [(0, (1, 1), 150, 1e-4), (1, (1, 1), 40, 1e-3), (0, (2, 2), 150, 1e-4)],
    ids=["setpoints", "with-nn-defenders", "2v2-setpoints"],
)
def test_compiled_step_flies_like_the_eager_one(
    write_small_set, tmp_path, nn_weight, team, steps, atol
):
    k, m = team
    write_small_set(
        tmp_path,
        f"scenario.strategy_mix.nn={nn_weight}",
        f"scenario.attackers={k}",
        f"scenario.defenders={m}",
    )

    def run(compile_step):
        env = make_env(
            "drone=attacker_v4",  # the tolerances above hold for its guided_velocity action
            f"env.compile_step={compile_step}",
            "env.time_limit=3",
            "env.scenario_order=random",
            scenarios=tmp_path,
            num_envs=8,
        )
        env.set_seed(3)
        torch.manual_seed(0)  # random actions come from torch's global generator
        return env, env.rollout(steps, break_when_any_done=False)

    eager_env, eager = run(False)
    compiled_env, compiled = run(True)
    assert compiled_env._advance is not compiled_env._advance_eager
    assert eager_env._advance == eager_env._advance_eager
    assert (compiled_env.defender_network is None) == (nn_weight == 0)
    check_env_specs(compiled_env, seed=0)
    assert eager["next", "done"].any()  # episodes ended and were reset along the way
    for key in eager["next"].keys(True, True):
        a, b = eager["next", key], compiled["next", key]
        if a.is_floating_point():
            torch.testing.assert_close(b, a, atol=atol, rtol=1e-5, msg=str(key))
        else:
            assert torch.equal(a, b), key


def test_time_limit_truncates(scenarios):
    env = make_env("env.time_limit=1.0", scenarios=scenarios, num_envs=4)
    td = env.rollout(10, break_when_any_done=False)
    assert td["next", "truncated"][:, -1].all() and not td["next", "truncated"][:, :-1].any()
    assert not td["next", "terminated"].any()


@pytest.mark.slow
@pytest.mark.parametrize("dynamics", ["velocity", "quadrotor"])
def test_no_nan_in_long_random_rollouts(scenarios, dynamics):
    steps = 1500 if dynamics == "velocity" else 300
    env = make_env(
        f"dynamics={dynamics}", "env.scenario_order=random", scenarios=scenarios, num_envs=32
    )
    env.set_seed(0)
    td = env.rollout(steps, break_when_any_done=False)
    for key in ("observation", "reward", "distance", "positions"):
        assert torch.isfinite(td["next", key]).all(), key
    assert td["next", "done"].any()  # episodes ended and were reset along the way


def test_defender_follows_its_route_to_the_end(write_small_set, tmp_path):
    route = "scenario.routes=[[[0,0,10],[0,6,10]]]"
    write_small_set(tmp_path, route, "scenario.params.defender_max_speed.low=4")
    env = make_env(route, "drone=attacker_v4", "env.time_limit=30", scenarios=tmp_path,
                   num_envs=8)  # fmt: skip
    hover = TensorDictModule(lambda o: o[..., :3] * 0, in_keys=["observation"], out_keys=["action"])
    td = env.rollout(300, hover, break_when_any_done=False)
    truncated = td["next", "truncated"].squeeze(-1)
    assert truncated.any(dim=1).all(), "every defender finishes its 2-setpoint route"
    first_end = truncated.float().argmax(dim=1)
    waypoints = td["next", "waypoint"].squeeze(-1)
    assert all(waypoints[i, first_end[i]] == 2 for i in range(8))


def test_follow_route_flies_to_its_target_and_holds_at_the_end():
    target = torch.tensor([[10.0, 0, 10], [10, 10, 10], [10, 10, 10]])
    pos = torch.tensor([[0.0, 0, 10], [10, 0, 10], [10, 10, 10]])
    done = torch.tensor([False, False, True])
    cmd = follow_route(pos, target, done, torch.full((3,), 2.0), 1.0)
    assert cmd.tolist() == [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 0]]
    cmd = follow_route(pos, target - 0.5, ~done, torch.full((3,), 2.0), 1.0)
    assert cmd.tolist() == [[0, 0, 0], [0, 0, 0], [-0.5, -0.5, -0.5]]


def test_nn_defender_without_network_is_refused(write_small_set, tmp_path):
    write_small_set(tmp_path, "scenario.strategy_mix.nn=1")
    with pytest.raises(ConfigError, match=r"env.defender_network: checkpoint: no file at /no"):
        make_env("env.defender_network=/no/such.pt", scenarios=tmp_path)
    run = tmp_path / "run"  # a run directory where its checkpoint file is asked for
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match=(
        rf"^env.defender_network: checkpoint: {re.escape(str(run))} is a folder, not a "
        rf"checkpoint file; a run's best is {re.escape(str(run / 'checkpoints' / 'best.pt'))}$"
    )):  # fmt: skip
        make_env(f"env.defender_network={run}", scenarios=tmp_path)
    env = make_env(scenarios=tmp_path)  # the shipped network
    with pytest.raises(ConfigError, match=r"scenarios ask for defender_strategy 'nn' but no "):
        parts = (env.dynamics, env.obs_fn, env.action_fn, env.reward_fn)
        PursuitEnv(
            **dict(zip(("dynamics", "observation", "action", "reward"), parts, strict=True)),
            scenarios=env.scenario_set,
        )
    # A learning defender flies itself: no network needed, none loaded.
    assert make_env("drone=defender_v1", scenarios=tmp_path).defender_network is None


def test_bad_env_option_is_refused(scenarios):
    with pytest.raises(ConfigError, match=r"env.scenario_order: unknown 'backwards'; valid"):
        make_env("env.scenario_order=backwards", scenarios=scenarios)
    with pytest.raises(ConfigError, match=r"dynamics.name: unknown 'rocket'; valid: velocity"):
        make_env("dynamics.name=rocket", scenarios=scenarios)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("drone=defender_v1", "reward=sparse"),
         r"^reward.terms.capture: 10 pays the defender for being caught; a defender's reward"),
        (("drone=attacker_v3", "reward=evasion"),
         r"^reward.terms.capture: -50 charges the attacker for catching"),
        (("drone=attacker_v3", "+reward.terms.route_progress=1"),
         r"^reward.terms.route_progress: is the defender's route, this run's learner is the "
         r"attacker"),
    ],
)  # fmt: skip
def test_a_reward_of_the_other_side_is_refused_by_training_and_warned_by_an_env(
    scenarios, overrides, message, caplog
):
    from rlplat.experiment.schema import validate_train_config

    with pytest.raises(ConfigError, match=message):
        validate_train_config(compose_config("train", list(overrides)))
    with caplog.at_level("WARNING", logger="rlplat.envs.pursuit"):
        make_env(*overrides, scenarios=scenarios)  # to fly policies: its reward is unused
    assert re.search(message[1:], caplog.text)


def test_make_env_flies_the_sets_own_config_as_training_does(write_small_set, tmp_path):
    # A set drawn in another vision ellipsoid flies in it, passed as an argument or through
    # the scenarios_dir override, as train.py flies it; not in the composed one.
    held = write_small_set(tmp_path / "set", "scenario.vision_semi_axes=[20.0,18.0,6.0]")
    for env in (make_env(scenarios=held.path), make_env(f"scenarios_dir={held.path}")):
        assert env.scenario_set.path == held.path
        assert env.semi_axes.tolist() == [20.0, 18.0, 6.0]
    with pytest.raises(ConfigError, match=r"^scenarios: given with scenarios_dir=.* too"):
        make_env(f"scenarios_dir={held.path}", scenarios=held.path)


@pytest.mark.parametrize(
    ("overrides", "kwargs", "message"),
    [
        (("env.capture_radius=-1",), {}, "env.capture_radius: must be a finite number > 0, got -1"),
        (("env.terminate_out_of_view=no",), {}, "env.terminate_out_of_view: must be true or false"),
        (("env.vision_semi_axes=[1,2]",), {}, "env.vision_semi_axes: must be 3 finite numbers"),
        (("env.pursuit_gain=-5",), {}, "env.pursuit_gain: must be a finite number > 0, got -5"),
        (("dynamics.physics_dt=-1",), {}, "dynamics.physics_dt: must be a finite number > 0"),
        ((), {"num_envs": 2.5}, "num_envs: must be an integer >= 1, got 2.5"),
        ((), {"num_envs": True}, "num_envs: must be an integer >= 1, got True"),
        ((), {"split": "tst"}, "split: unknown 'tst'; valid: train, val, test"),
        ((), {"scenarios": 42}, "scenarios: must be a ScenarioSet, a directory or None, got 42"),
        ((), {"share": (2, 2)}, "share: must be (index, count) with 0 <= index < count"),
    ],
)  # fmt: skip
def test_make_env_refuses_bad_input_in_one_line_naming_it(scenarios, overrides, kwargs, message):
    kwargs.setdefault("scenarios", scenarios)
    with pytest.raises(ConfigError) as refused:
        make_env(*overrides, **kwargs)
    assert str(refused.value).startswith(message) and "\n" not in str(refused.value)


def test_workers_of_a_serial_env_share_one_walk_of_the_split(scenarios):
    from torchrl.envs import SerialEnv

    workers = SerialEnv(
        2, [lambda i=i: make_env(scenarios=scenarios, share=(i, 2)) for i in range(2)]
    )
    batch = make_env(scenarios=scenarios, num_envs=2)
    assert workers.reset()["scenario_index"].flatten().tolist() == [0, 1]
    assert batch.reset()["scenario_index"].flatten().tolist() == [0, 1]
    workers.close()


@pytest.mark.parametrize("order", ["shuffled", "random", "weighted"])
def test_seeded_workers_split_one_drawn_walk_as_one_batch_does(scenarios, order):
    """Workers that draw their walk split it too (each keeps its share of the same draws) once
    seeded alike; 32 resets of two workers fly what a batch of two flies, so a shuffled pass of
    the 64 train scenarios flies each once."""
    from torchrl.envs import SerialEnv

    setting = "shuffled" if order == "weighted" else order
    args = (f"env.scenario_order={setting}",)
    workers = SerialEnv(2, [lambda i=i: make_env(*args, scenarios=scenarios, share=(i, 2))
                            for i in range(2)])  # fmt: skip
    batch = make_env(*args, scenarios=scenarios, num_envs=2)
    if order == "weighted":  # draws in proportion to weights, as failure_weight sets them
        weights = torch.arange(64, dtype=torch.float64) % 3
        batch.sampler.set_weights(weights)
        workers.start()
        for env in workers._envs:
            env.sampler.set_weights(weights)
    workers.set_seed(5, static_seed=True)
    batch.set_seed(5)

    def walk(env):
        return torch.stack([env.reset()["scenario_index"].flatten() for _ in range(32)])

    flown = walk(workers)
    assert torch.equal(flown, walk(batch))
    assert not torch.equal(flown[:, 0], flown[:, 1])  # the two workers fly different scenarios
    if order == "shuffled":
        assert sorted(flown.flatten().tolist()) == list(range(64))
    workers.close()


def test_a_copy_of_a_compiled_env_steps_its_own_state(scenarios):
    import copy
    import pickle

    env = make_env("env.compile_step=true", scenarios=scenarios, num_envs=2)
    env.reset()
    twin = copy.deepcopy(env)
    twin.rollout(3, break_when_any_done=False)
    assert env.step_count.tolist() == [0, 0] and twin.step_count.tolist() == [3, 3]
    thawed = pickle.loads(pickle.dumps(env))
    assert thawed.compile_step and thawed._advance is not env._advance


def test_an_observation_must_name_every_feature():
    class Unnamed(OBSERVATIONS["relative_state"]):
        own_layout = ("v", "s")  # one more entry than relative_state names

    with pytest.raises(TypeError, match=r"^Unnamed.own_names: 1 names for the 2 entries"):
        Unnamed()


def test_default_scenarios_are_generated_once_into_the_cache(small_sizes, tmp_path, monkeypatch):
    import rlplat.experiment.factory as factory

    monkeypatch.setattr(factory, "CACHE_DIR", tmp_path)
    env = make_env(*small_sizes, num_envs=2)
    (cached,) = (tmp_path / "scenarios").iterdir()
    assert (cached / "manifest.json").exists()
    assert len(env.scenarios) == 64
    mtime = (cached / "manifest.json").stat().st_mtime_ns
    make_env(*small_sizes)
    assert (cached / "manifest.json").stat().st_mtime_ns == mtime


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.zeros(2, 4), r"action: shape \(2, 4\), expected \(2, 3\)"),
        (torch.tensor([[0.0, float("nan"), 0], [0, 0, 0]]), "action: contains NaN or inf"),
        (torch.tensor([[0.0, 0, 0], [float("inf"), 0, 0]]), "action: contains NaN or inf"),
    ],
)
def test_bad_actions_are_refused(scenarios, action, match):
    env = make_env("drone=attacker_v4", scenarios=scenarios, num_envs=2)  # a 3-d action
    td = env.reset()
    with pytest.raises(ValueError, match=match):
        env.step(td.set("action", action))


def test_missing_scenario_set_is_a_clear_error(tmp_path):
    from rlplat.errors import ScenarioFileError

    with pytest.raises(ScenarioFileError, match="nowhere"):
        make_env(scenarios=tmp_path / "nowhere")
