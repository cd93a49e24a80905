"""The config schema: every option composes and validates, bad values fail in one line that
names them, a resume refuses a changed config, and algo/sac_paper is sac plus its changes."""

import copy
import functools

import pytest
import torch
import yaml
from omegaconf import OmegaConf

from rlplat.errors import ConfigError
from rlplat.experiment.command_line import check_command_line
from rlplat.experiment.config import CONF_DIR, compose_config
from rlplat.experiment.schema import (
    COMPONENTS,
    POLICIES,
    RESUME_FREE,
    TRAIN_RULES,
    Num,
    Opt,
    check_resume,
    config_diff,
    knobs,
    validate_evaluate_config,
    validate_train_config,
)
from rlplat.scenarios import SPLITS

GROUPS = ("scenario", "dynamics", "observation", "action", "reward", "algo", "drone", "logger")
OPTIONS = [f"{g}={p.stem}" for g in GROUPS for p in sorted((CONF_DIR / g).glob("*.yaml"))]


def train_error(*overrides: str) -> str:
    with pytest.raises(ConfigError) as info:
        validate_train_config(compose_config("train", overrides))
    return str(info.value)


def evaluate_error(*overrides: str) -> str:
    with pytest.raises(ConfigError) as info:
        validate_evaluate_config(compose_config("evaluate", overrides))
    return str(info.value)


# Every option composes and validates


def test_every_group_has_options():
    assert {o.split("=")[0] for o in OPTIONS} == set(GROUPS)
    assert "algo=sac_paper" in OPTIONS and "drone=defender_v1" in OPTIONS


# What an option needs besides the defaults: AirSim flies one env per simulator; no scripted
# start can be flown through an action that sets the guidance law; a reward is its side's.
NEEDS = {
    "dynamics=airsim": ["algo.num_envs=1"],
    "action=guidance_law": ["algo.init_policy=random"],
    "action=augmented_law": ["algo.init_policy=random"],
    "reward=evasion": ["drone=defender_v1"],  # the defender's reward
}


def test_a_reward_chosen_on_the_command_line_is_that_rewards_whatever_the_bundle():
    # A bundle chooses its reward as a group (attacker_v13: shaped_capture_long), so a reward
    # given on the command line replaces all of it: none of the bundle's weights stay.
    sparse = compose_config("train", ["drone=attacker_v1", "reward=sparse"]).reward
    for drone in ("attacker_v6", "attacker_v11", "attacker_v13"):
        assert compose_config("train", [f"drone={drone}", "reward=sparse"]).reward == sparse
    assert sparse.terms.ground_contact == -100.0
    assert compose_config("train", []).reward.terms.ground_contact == -600.0  # the bundle's own


@pytest.mark.parametrize("option", [None, *OPTIONS])
def test_train_option_composes_and_validates(option):
    overrides = [option, *NEEDS.get(option, [])] if option else []
    validate_train_config(compose_config("train", overrides))


def test_attacker_v9_flies_a_corrected_law_and_a_group_choice_replaces_it():
    # conf/action/corrected_law.yaml is no registry key: guidance_law with a correction of 2.
    bundle = compose_config("train", ["drone=attacker_v9"])
    assert bundle.observation.name == "pursuit_route" and bundle.reward.terms.capture == 100.0
    assert bundle.action.name == "guidance_law" and bundle.action.correction_reach == 2.0
    # A group choice on the command line replaces the bundle's, its correction included.
    law = compose_config("train", ["drone=attacker_v9", "action=guidance_law"])
    assert law.action.correction_reach == 0.0 and law.observation.name == "pursuit_route"
    guided = compose_config("train", ["drone=attacker_v9", "action=guided_velocity"])
    assert guided.action.name == "guided_velocity" and "correction_reach" not in guided.action
    validate_train_config(guided)  # its scripted start is the bundle's random one


@pytest.mark.parametrize("drone", [o.split("=")[1] for o in OPTIONS if o.startswith("drone=")])
def test_every_bundle_takes_the_plain_action_from_the_command_line(drone):
    # A bundle's action knobs live in its action option (route_law_held, route_law_gated), so
    # another action on the command line replaces them with it.
    cfg = compose_config("train", [f"drone={drone}", "action=velocity"])
    assert OmegaConf.to_container(cfg.action) == {"name": "velocity"}
    validate_train_config(cfg)


def test_attacker_v13_gates_the_law_of_attacker_v12():
    v12, v13 = (compose_config("train", [f"drone=attacker_v{i}"]) for i in (12, 13))
    assert (v12.action.homing_time, v12.action.start_lag, v12.action.gate_high) == (0.5, 0.5, 0.0)
    gate = {"gate_low": 1.5, "gate_high": 2.5, "gate_unreachable": False}
    assert {**v12.action, **gate} == dict(v13.action)
    # and explores with noise correlated in time, where the algorithm's default draws afresh
    assert (v12.algo.noise_correlation, v13.algo.noise_correlation) == (0.0, 0.98)


def test_attacker_v14_is_attacker_v13_heading_off_and_the_default():
    v13, v14, default = (
        OmegaConf.to_container(compose_config("train", o), resolve=True)
        for o in (["drone=attacker_v13"], ["drone=attacker_v14"], [])
    )
    assert default == v14 and v14["drone"]["name"] == "attacker_v14"
    assert (v13["action"]["unreachable"], v14["action"]["unreachable"]) == ("chase", "head_off")
    # Nothing else differs: the same seed trains attacker_v13 with action.unreachable=head_off.
    v13["drone"]["name"], v13["action"]["unreachable"] = "attacker_v14", "head_off"
    assert v13 == v14
    # The action is the bundle's option, so a group choice still replaces all of it.
    gated = compose_config("train", ["drone=attacker_v14", "action=route_law_gated"])
    assert gated.action.unreachable == "chase" and gated.action.gate_high == 2.5


@pytest.mark.parametrize(
    "overrides",
    [
        ["env.capture_radius=2"],  # an int where a float is expected
        ["train.max_minutes=null", "train.threads=2", "env.attackers=1"],
        ["algo.target_entropy=-3", "algo.gamma=0", "algo.action_margin=1"],
        ["logger=wandb", "logger.mode=online", "logger.project=drones"],
        ["drone=defender_v1", "algo=sac_paper", "algo.init_policy=random"],
        ["scenario=pursuit_2v1", "env.attackers=2", "dynamics=quadrotor"],
        ["scenarios_dir=/some/set", "env.attackers=3"],  # the set on disk is checked on load
        ["~reward.distance_scale", "~dynamics.drag_z"],  # the class's default applies
    ],
    ids=lambda o: " ".join(o),
)
def test_train_valid_overrides(overrides):
    validate_train_config(compose_config("train", overrides))


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        *[[f"policy={p}"] for p in POLICIES],
        *[[f"split={s}"] for s in SPLITS],
        ["ckpt=last", "threads=1", "trajectories=0", "speed_ratio_bins=[1]", "attackers=1"],
        ["compare=true", "device=cpu", "out_dir=null", "scenarios_dir=/some/set"],
    ],
    ids=lambda o: " ".join(o) or "default",
)
def test_evaluate_config_validates(overrides):
    validate_evaluate_config(compose_config("evaluate", ["run_dir=runs/x", *overrides]))


def test_a_device_this_machine_lacks_is_one_line_before_any_work():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    missing = f"cuda:{count}"  # one past the last device there is (cuda:0 on a CPU machine)
    with pytest.raises(ConfigError) as e:
        validate_train_config(compose_config("train", [f"train.device={missing}"]))
    assert str(e.value).startswith(f"train.device: '{missing}' is not available on this machine")
    with pytest.raises(ConfigError, match=rf"^device: '{missing}' is not available"):
        validate_evaluate_config(compose_config("evaluate", ["run_dir=x", f"device={missing}"]))
    if count:
        validate_train_config(compose_config("train", ["train.device=cuda:0"]))


@pytest.mark.parametrize("group", sorted(COMPONENTS))
def test_every_component_knob_has_a_rule(group):
    registry, rules, factory_args = COMPONENTS[group]
    for cls in registry.values():
        assert set(knobs(cls, factory_args)) <= set(rules), cls.__name__


# Bad values fail in one line naming the field and the value

BAD_TRAIN = [
    (["env.capture_radius=-1"], "env.capture_radius", "-1"),
    (["algo.actor_lr=nan"], "algo.actor_lr", "nan"),
    (["algo.critic_lr=inf"], "algo.critic_lr", "inf"),
    (["reward.terms.capture=-inf"], "reward.terms.capture", "-inf"),
    (["env.time_limit=0"], "env.time_limit", "0"),
    (["env.ground_altitude=-0.5"], "env.ground_altitude", "-0.5"),
    (["env.vision_semi_axes=[48,42]"], "env.vision_semi_axes", "[48, 42]"),
    (["env.scenario_order=backwards"], "env.scenario_order", "'backwards'"),
    (["env.compile_step=maybe"], "env.compile_step", "'maybe'"),
    (["env.attackers=0"], "env.attackers", "0"),
    (["env.attackers=2"], "env.attackers", "2"),  # the configured scenarios have 1
    (["env.attackers=5"], "env.attackers", "5"),  # before the buffer it would outgrow
    (["env.time_limit=0.05"], "env.time_limit", "shorter than one control period"),
    (["scenario.n_test=0"], "scenario.n_test", "got 0"),  # training tests at its end
    (["scenario.n_val=0"], "scenario.n_val", "got 0"),
    (["seed=-1"], "seed", "-1"),
    (["seed=0.5"], "seed", "0.5"),
    (["resume=yes"], "resume", "'yes'"),
    (["scenarios_dir=''"], "scenarios_dir", "''"),
    (["train.total_frames=1.5"], "train.total_frames", "1.5"),
    (["train.total_frames=0"], "train.total_frames", "0"),
    (["train.max_minutes=0"], "train.max_minutes", "0"),
    (["train.eval_every_frames=abc"], "train.eval_every_frames", "'abc'"),
    (["train.threads=0"], "train.threads", "0"),
    (["train.device=gpu"], "train.device", "'gpu'"),
    (["algo.batch_size=abc"], "algo.batch_size", "'abc'"),
    (["algo.num_envs=true"], "algo.num_envs", "True"),
    (["algo.gamma=1.0"], "algo.gamma", "1.0"),
    (["algo.tau=0"], "algo.tau", "0"),
    (["algo.n_steps=0"], "algo.n_steps", "0"),
    (["algo.init_noise=-0.1"], "algo.init_noise", "-0.1"),
    (["algo.action_margin=1.5"], "algo.action_margin", "1.5"),
    (["algo.target_entropy=high"], "algo.target_entropy", "'high'"),
    (["algo.actor_cells=[64,0]"], "algo.actor_cells", "[64, 0]"),
    (["algo.critic_cells=[]"], "algo.critic_cells", "[]"),
    (["algo.activation=gelu"], "algo.activation", "relu, tanh, elu"),
    (["algo.loss_function=huber"], "algo.loss_function", "'huber'"),
    (["algo.potential_key=speed"], "algo.potential_key", "'speed'"),
    (["algo.init_policy=x"], "algo.init_policy", "unknown 'x'; valid: random, pure_pursuit"),
    (["algo.init_policy=setpoint_follower"], "algo.init_policy", "'setpoint_follower'"),
    (["drone=defender_v1", "algo.init_policy=pure_pursuit"], "algo.init_policy", "pure_pursuit"),
    (
        ["drone=attacker_v13", "algo.init_policy=proportional_navigation"],
        "algo.init_policy",
        "a gated correction flies only its law where the defender keeps its route); valid: "
        "random, route_intercept",
    ),
    (["action.gate_high=-1"], "action.gate_high", "-1"),
    (["algo.evader_weight=0"], "algo.evader_weight", "0"),
    (["drone=defender_v1", "algo.evader_weight=3"], "algo.evader_weight", "is the defender"),
    (["algo.frames_per_batch=100"], "algo.frames_per_batch", "100"),
    (["algo.buffer_size=1000"], "algo.buffer_size", "1000"),
    (["+algo.foo=1"], "algo.foo", "valid: name, num_envs"),
    (["+train.foo=1"], "train.foo", "valid: total_frames"),
    (["+env.foo=1"], "env.foo", "valid: control_period"),
    (["+foo=1"], "foo", "unknown key"),
    (["~algo.actor_lr"], "algo.actor_lr", "missing"),
    (["drone.learner=pilot"], "drone.learner", "'pilot'"),
    (["+logger.project=x"], "logger.project", "valid: backend"),  # csv has no project
    (["logger=wandb", "logger.mode=disabled"], "logger.mode", "'disabled'"),
    (["logger.backend=mlflow"], "logger.backend", "'mlflow'"),
    (["dynamics.name=rocket"], "dynamics.name", "'rocket'"),
    (["dynamics.tau_xy=0"], "dynamics.tau_xy", "0"),
    (["dynamics.drag_z=-1"], "dynamics.drag_z", "-1"),
    (["dynamics.physics_dt=0.5"], "dynamics.physics_dt", "0.5"),  # > env.control_period
    (["dynamics=quadrotor", "dynamics.physics_dt=0.1"], "dynamics.physics_dt", "too coarse"),
    (["+dynamics.max_tilt=0.5"], "dynamics.max_tilt", "valid: name, physics_dt"),
    (["dynamics=quadrotor", "dynamics.max_tilt=2"], "dynamics.max_tilt", "2"),
    (["dynamics=quadrotor", "dynamics.max_rotor_thrust=2"], "dynamics.max_rotor_thrust", "2"),
    (["dynamics=airsim", "dynamics.endpoints=[foo]"], "dynamics.endpoints", "'foo'"),
    (["dynamics=airsim", "dynamics.endpoints=[127.0.0.1:0]"], "dynamics.endpoints", ":0'"),
    (["dynamics=airsim", "dynamics.endpoints=[]"], "dynamics.endpoints", "[]"),
    (
        ["dynamics=airsim", "algo.num_envs=1", "dynamics.timeout_s=0.05"],
        "dynamics.timeout_s",
        "0.05",
    ),  # fmt: skip
    (  # AirSim runs ClockSpeed 2.5 at 2: a step is 0.05 s of its wall clock, not 0.04
        [
            "dynamics=airsim",
            "algo.num_envs=1",
            "dynamics.clock_speed=2.5",
            "dynamics.timeout_s=0.045",
        ],
        "dynamics.timeout_s",
        "= 0.05 s",
    ),  # fmt: skip
    (
        ["dynamics=airsim", "dynamics.on_time_mismatch=ignore"],
        "dynamics.on_time_mismatch",
        "'ignore'",
    ),  # fmt: skip
    (["dynamics=airsim", "dynamics.spawn={Attacker:[1,2]}"], "dynamics.spawn", "[1, 2]"),
    (["dynamics=airsim"], "algo.num_envs", "64, dynamics.endpoints names 1 simulator"),
    (
        ["dynamics=airsim", "algo.num_envs=1", "env.compile_step=true"],
        "env.compile_step",
        "true",
    ),  # fmt: skip
    (["observation.position_scale=0"], "observation.position_scale", "0"),
    (["observation.name=lidar"], "observation.name", "'lidar'"),
    (["+action.knob=2"], "action.knob", "unknown key"),
    (["reward.distance_scale=0"], "reward.distance_scale", "0"),
    (["+reward.terms.bonus=1"], "reward.terms.bonus", "valid: capture"),
    (["~reward.terms"], "reward.terms", "missing"),
    (["reward.terms=null"], "reward.terms", "None"),
    (["scenario.attackers=0"], "scenario.attackers", "0"),
    (["scenario.n_train=-5"], "scenario.n_train", "-5"),
    (["algo.priority_alpha=1.5"], "algo.priority_alpha", "1.5"),
    (["algo.priority_beta=-0.1"], "algo.priority_beta", "-0.1"),
    # an attacker's component for the defender: said before the scripted start it implies
    (["drone=defender_v1", "action=guidance_law"], "action", "flies attackers; this run's"),
    (["drone=defender_v1", "observation=pursuit_conform"], "observation", "reads the defender's"),
    (["drone=defender_v1", "observation=pursuit_intercept"], "observation", "pursuit_intercept"),
]


@pytest.mark.parametrize(
    ("overrides", "field", "value"), BAD_TRAIN, ids=[" ".join(o) for o, _, _ in BAD_TRAIN]
)
def test_bad_train_value_fails_in_one_line(overrides, field, value):
    message = train_error(*overrides)
    assert message.startswith(f"{field}: ") and value in message
    assert "\n" not in message


@pytest.mark.parametrize("observation", ["pursuit_conform", "pursuit_intercept"])
def test_an_attackers_observation_for_the_defender_reads_alike_in_training_and_make_env(
    observation, scenarios
):
    from rlplat import make_env

    overrides = ("drone=defender_v1", f"observation={observation}")
    with pytest.raises(ConfigError) as info:
        make_env(*overrides, scenarios=scenarios, num_envs=2)
    assert str(info.value) == train_error(*overrides)
    assert str(info.value).startswith(f"observation: {observation} reads the defender's route")


def _numbers(rules):
    return [k for k, r in rules.items() if isinstance(r.rule if isinstance(r, Opt) else r, Num)]


NUMERIC = [[f"++{k}=nan"] for k in _numbers(TRAIN_RULES)]  # inf: see BAD_TRAIN
for _group, (_registry, _rules, _args) in COMPONENTS.items():
    for _name, _cls in _registry.items():
        NUMERIC += [
            [f"{_group}={_name}", f"++{_group}.{k}=nan"]
            for k, default in knobs(_cls, _args).items()
            if not isinstance(default, str)  # a choice of names (action.unreachable)
        ]


@functools.cache
def _composed(*overrides: str):
    """The train config of ``overrides``, composed once per worker (never changed: copied)."""
    return compose_config("train", overrides)


@pytest.mark.parametrize("overrides", NUMERIC, ids=lambda o: " ".join(o))
def test_every_number_refuses_nan(overrides):
    # What `++field=nan` composes to, set on its component's config (each composed once); a
    # NaN typed through Hydra itself is BAD_TRAIN's.
    *component, last = overrides
    field, value = last.removeprefix("++").split("=")
    cfg = copy.deepcopy(_composed(*component))
    OmegaConf.update(cfg, field, float(value), force_add=True)
    with pytest.raises(ConfigError) as info:
        validate_train_config(cfg)
    message = str(info.value)
    assert message.startswith(f"{field}: ") and f"got {value}" in message


BAD_EVALUATE = [
    (
        ["run_dir=r", "dynamics=airsim", "dynamics.endpoints=[host:99999]"],
        "dynamics.endpoints",
        "'host:99999'",
    ),  # fmt: skip
    (["run_dir=r", "dynamics=airsim", "+dynamics.speed=2"], "dynamics.speed", "unknown key"),
    (["run_dir=r", "trajectories=-1"], "trajectories", "-1"),
    (["run_dir=r", "trajectories=2.5"], "trajectories", "2.5"),
    (["run_dir=r", "speed_ratio_bins=[1.0,0.5]"], "speed_ratio_bins", "[1.0, 0.5]"),
    (["run_dir=r", "speed_ratio_bins=[]"], "speed_ratio_bins", "[]"),
    (["run_dir=r", "speed_ratio_bins=[0,1]"], "speed_ratio_bins", "[0, 1]"),
    (["run_dir=r", "speed_ratio_bins=[1,nan]"], "speed_ratio_bins", "nan"),
    (["run_dir=r", "policy=magic"], "policy", "'magic'; valid: checkpoint, onnx, c, pure_pursuit"),
    (["run_dir=r", "split=holdout"], "split", "'holdout'; valid: train, val, test"),
    (["run_dir=r", "threads=0"], "threads", "0"),
    (["run_dir=r", "device=gpu"], "device", "'gpu'"),
    (["run_dir=r", "attackers=0"], "attackers", "0"),
    (["run_dir=r", "plots=sometimes"], "plots", "'sometimes'"),
    (["run_dir=r", "policy=pure_pursuit", "ckpt=last"], "ckpt", "'last'"),
    (["run_dir=r", "ensemble=r2"], "ensemble", "'r2'"),
    (["run_dir=r", "policy=pure_pursuit", "ensemble=[r2]"], "ensemble", "policy=pure_pursuit"),
    (["run_dir=r", "+foo=1"], "foo", "valid: run_dir, policy"),
    ([], "run_dir", "???"),
]


@pytest.mark.parametrize(
    ("overrides", "field", "value"), BAD_EVALUATE, ids=[" ".join(o) for o, _, _ in BAD_EVALUATE]
)
def test_bad_evaluate_value_fails_in_one_line(overrides, field, value):
    message = evaluate_error(*overrides)
    assert message.startswith(f"{field}: ") and value in message
    assert "\n" not in message


# Resume


def resolved(*overrides: str) -> dict:
    return OmegaConf.to_container(compose_config("train", overrides), resolve=True)


def test_config_diff_lists_changed_added_and_removed_keys_sorted():
    saved = {"env": {"capture_radius": 1.2, "gone": 1}, "algo": {"cells": [64, 64]}, "seed": 0}
    current = {"env": {"capture_radius": 2.0, "new": {}}, "algo": {"cells": [64, 32]}, "seed": 0}
    expected = ["algo.cells", "env.capture_radius", "env.gone", "env.new"]
    assert config_diff(saved, current) == expected
    assert config_diff(saved, saved) == []


def test_config_diff_ignores_what_a_resume_may_change():
    saved = resolved()
    current = resolved(
        "resume=true",
        "train.total_frames=9000000",
        "train.max_minutes=null",
        "train.threads=1",
        "train.progress=false",
        "env.compile_step=true",
        "algo.compile=false",
        "logger=wandb",
    )
    assert config_diff(saved, current) == []
    assert "train.total_frames" in config_diff(saved, current, ignore=())
    assert "logger.project" in config_diff(saved, current, ignore=["resume"])
    assert {"resume", "train.total_frames", "logger.*"} <= set(RESUME_FREE)


def test_config_diff_sees_through_a_saved_config_yaml(tmp_path):
    path = tmp_path / "config.yaml"  # as a run writes it
    path.write_text(OmegaConf.to_yaml(resolved("seed=3")))
    saved = OmegaConf.load(path)
    assert config_diff(saved, resolved("seed=3", "resume=true")) == []
    assert config_diff(saved, compose_config("train", ["seed=4"])) == ["seed"]


def test_check_resume_accepts_a_longer_budget():
    check_resume(resolved(), resolved("resume=true", "train.total_frames=4000000"))


def test_check_resume_refuses_a_changed_config_in_one_line():
    saved = resolved("drone=attacker_v4")  # eq. 3: a capture pays 10
    current = resolved(
        "drone=attacker_v4", "resume=true", "env.capture_radius=2.0", "reward.terms.capture=5.0"
    )
    with pytest.raises(ConfigError) as info:
        check_resume(saved, current)
    message = str(info.value)
    assert message.startswith("resume: the config differs from the run's own in ")
    assert "env.capture_radius (1.2 -> 2.0), reward.terms.capture (10.0 -> 5.0);" in message
    assert "only resume, train.total_frames, train.max_minutes" in message
    assert "\n" not in message


def test_a_run_saved_before_a_key_existed_resumes_with_its_neutral_value():
    from rlplat.experiment.schema import ADDED_KEYS

    saved = resolved("drone=attacker_v6")
    del saved["algo"]["failure_weight"], saved["action"]["accel_lead"]
    del saved["action"]["accel_reach"], saved["algo"]["actor_average"]
    del saved["action"]["correction_reach"]
    added = {"algo.failure_weight", "action.accel_lead", "action.accel_reach",
             "algo.actor_average", "action.correction_reach"}  # fmt: skip
    assert added <= set(ADDED_KEYS)
    check_resume(saved, resolved("drone=attacker_v6", "resume=true"))
    # Any other value is a change, named as one.
    with pytest.raises(ConfigError, match=r"action\.accel_lead \(absent -> 0\.9\)"):
        check_resume(saved, resolved("drone=attacker_v7", "resume=true"))
    # The route law's later settings: a run of the default drone saved before them resumes.
    saved = resolved("drone=attacker_v10")
    for key in ("start_lag", "gate_low", "gate_high", "horizon", "unreachable"):
        del saved["action"][key]
    check_resume(saved, resolved("drone=attacker_v10", "resume=true"))
    with pytest.raises(ConfigError, match=r"action\.horizon \(absent -> 120\)"):
        check_resume(saved, resolved("drone=attacker_v10", "action.horizon=120", "resume=true"))
    with pytest.raises(ConfigError, match=r"action\.unreachable \(absent -> 'head_off'\)"):
        check_resume(saved, resolved("drone=attacker_v10", "action.unreachable=head_off",
                                     "resume=true"))  # fmt: skip
    # An AirSim run saved before dynamics.vehicles existed.
    saved = resolved("dynamics=airsim")
    del saved["dynamics"]["vehicles"]
    check_resume(saved, resolved("dynamics=airsim", "resume=true"))
    with pytest.raises(ConfigError, match=r"dynamics\.vehicles \(absent -> \['A', 'D'\]\)"):
        check_resume(saved, resolved("dynamics=airsim", "dynamics.vehicles=[A,D]", "resume=true"))


def test_check_resume_names_added_and_removed_keys():
    saved = resolved()
    current = resolved("+reward.terms.proximity=-1.0", "~reward.terms.in_view_step")
    with pytest.raises(ConfigError, match=r"proximity \(absent -> -1.0\)"):
        check_resume(saved, current)
    with pytest.raises(ConfigError, match=r"in_view_step \(-0.1 -> absent\)"):
        check_resume(saved, current)


# algo/sac_paper: sac plus what the paper changes

#: What algo/sac_paper.yaml states: its differences from algo/sac.yaml.
SAC_PAPER_CHANGES = {
    "name": "sac_paper",
    "num_envs": 1,
    "frames_per_batch": 1,
    "init_random_frames": 100,
    "init_policy": "random",
    "utd_ratio": 1.0,
    "batch_size": 128,
    "n_steps": 1,
    "potential_weight": 0.0,
    "actor_lr": 1.0e-3,
    "alpha_init": 1.0,
    "action_margin": 0.0,
    "compile": False,
}
#: What it keeps of algo/sac.yaml (Stable-Baselines3's values too).
SAC_PAPER_KEPT = {
    "init_noise": 0.3,
    "noise_correlation": 0.0,
    "buffer_size": 1000000,
    "priority_alpha": 0.0,  # SB3: uniform draws
    "priority_beta": 0.4,
    "gamma": 0.99,
    "potential_key": "distance",
    "tau": 0.005,
    "critic_lr": 1.0e-3,
    "alpha_lr": 1.0e-3,
    "target_entropy": "auto",
    "loss_function": "l2",
    "actor_cells": [64, 64],
    "critic_cells": [64, 64],
    "activation": "relu",
    "actor_zero_mean": False,
    "actor_init_std": None,
    "actor_warmup_updates": 0,
    "actor_average": 0.0,
    "anchor_weight": 0.0,
    "failure_weight": 1.0,
    "failure_evaders_only": False,
    "evader_weight": 1.0,
    "demonstrations": [],
    "demonstration_repeat": 4,
    "self_imitation": 0.0,
    "self_imitation_every": 2,
    "self_imitation_truncated": "drop",
}


def test_sac_paper_is_sac_plus_its_changes():
    # attacker_v3 sets no algo value of its own (attacker_v4 and later bundles set some)
    sac = resolved("algo=sac", "drone=attacker_v3")["algo"]
    paper = resolved("algo=sac_paper", "drone=attacker_v3")["algo"]
    assert paper == {**SAC_PAPER_CHANGES, **SAC_PAPER_KEPT}
    assert list(paper) == list(sac)  # same key order as before: composed from sac
    assert {k for k in sac if sac[k] != paper[k]} == set(SAC_PAPER_CHANGES)
    raw = yaml.safe_load((CONF_DIR / "algo" / "sac_paper.yaml").read_text())
    assert raw.pop("defaults") == ["sac", "_self_"]
    assert raw == SAC_PAPER_CHANGES  # states only what differs


def test_a_drone_bundle_still_sets_sac_paper_values():
    algo = resolved("algo=sac_paper", "drone=defender_v1")["algo"]
    assert algo["init_policy"] == "setpoint_follower" and algo["num_envs"] == 1


# The command line, before Hydra starts (rlplat.experiment.command_line): one line per mistake.
@pytest.mark.parametrize(
    "argv, line",
    [
        (["algo.gama=0.9"], "algo.gama: no such setting (did you mean algo.gamma?)"),
        (["observation.nope.x=1"], "observation.nope: no such setting (observation has name, "),
        (
            ["drone=attacker_v99"],
            "drone=attacker_v99: no such option (valid: attacker_v1, "
            "attacker_v2, attacker_v3, attacker_v4, attacker_v5, attacker_v6, attacker_v7, "
            "attacker_v8, attacker_v9, attacker_v10, ",
        ),  # fmt: skip
        (["hydra/launcher=nope"], "hydra/launcher=nope: no such option (valid: basic, cluster, "),
        (["algo.gamma=[1"], "algo.gamma=[1: no viable alternative at input '[1'"),
        (["seed=0,1"], "Ambiguous value for argument 'seed=0,1' "),  # a sweep without -m
        (["-m", "seed=0,-1"], "seed: must be an integer in [0, 4294967295], got -1"),
        (["-m", "seed=0,1", "algo.gamma=0.9,2"], "algo.gamma: must be a finite number in [0, 1)"),
        (["hydra.mode=MULTIRUN", "seed=0,-1"], "seed: must be an integer in [0, 4294967295]"),
        (["env.time_limit.x=1"], "env.time_limit.x: no such setting (env.time_limit has none)"),
        # A group picks one option: Hydra composes a list's on top of each other, fails on null.
        (
            ["drone=[attacker_v13,attacker_v1]"],
            "drone=[attacker_v13,attacker_v1]: a config group "
            "takes one option (valid: attacker_v1, attacker_v2, ",
        ),  # fmt: skip
        (["reward=null"], "reward=null: a config group takes one option (valid: evasion, shaped"),
        (["+dynamics=[velocity]"], "dynamics=[velocity]: a config group takes one option"),
        # What reads through a node that the command line replaced or removed names that node.
        (["env=foo"], "env: must be a mapping, got 'foo' (action.gain reads env.pursuit_gain)"),
        (["~env"], "env: missing (action.gain reads env.pursuit_gain)"),
        (["scenario.min_distance=-1"], "scenario.min_distance: must be >= 0 m, got -1.0"),
        (
            ["reward.terms=[1,2]"],
            "Error merging override reward.terms=[1,2]: Cannot merge DictConfig with ListConfig",
        ),  # fmt: skip
        (["--cfg", "job", "algo.gama=1"], "algo.gama: no such setting"),  # shown, not checked
        # Hydra's own refusals of its flags: a usage of many lines, or a traceback.
        (["--nope"], "--nope: not an option of this command; overrides are KEY=VALUE"),
        (
            ["seed=1", "--cfg", "job", "algo.gamma=0.9"],
            "algo.gamma=0.9: the overrides go together, all before or all after the flags",
        ),
        (["-m", "seed=0,1", "--cfg", "job"], "--multirun --cfg: one of them at a time"),
    ],
)
def test_a_bad_command_line_is_one_line_before_hydra_starts(argv, line):
    with pytest.raises(ConfigError) as e:
        check_command_line("train", argv, validate_train_config)
    assert str(e.value).startswith(line) and "\n" not in str(e.value)


@pytest.mark.parametrize("name", ["conf", "with,comma", "br]ack", "quo'te", "back\\slash"])
def test_a_config_dir_of_ones_own_groups_is_checked_with_them(tmp_path, name):
    # --config-dir adds a user's own options to the groups; the check composes with them, as
    # Hydra will (it used to skip the check, so a bad value surfaced inside the run), wherever
    # the folder is.
    tmp_path = tmp_path / name
    (tmp_path / "drone").mkdir(parents=True)
    (tmp_path / "drone" / "my_drone.yaml").write_text(
        "# @package _global_\ndefaults:\n  - attacker_v3\ndrone:\n  name: my_drone\n"
    )
    seen = []
    check_command_line("train", ["--config-dir", str(tmp_path), "drone=my_drone"], seen.append)
    assert [c.drone.name for c in seen] == ["my_drone"]
    with pytest.raises(ConfigError, match=r"^env.capture_radius: must be a finite number > 0"):
        check_command_line(
            "train",
            ["--config-dir", str(tmp_path), "drone=my_drone", "env.capture_radius=-1"],
            validate_train_config,
        )
    with pytest.raises(ConfigError, match=r"^drone=nope: no such option \(valid: .*my_drone"):
        check_command_line("train", ["-cd", str(tmp_path), "drone=nope"], seen.append)


def test_every_job_of_a_sweep_is_checked():
    seen = []
    check_command_line("train", ["-m", "seed=0,1,2", "algo=sac,sac_paper"], seen.append)
    assert sorted((c.seed, c.algo.name) for c in seen) == [
        (s, a) for s in (0, 1, 2) for a in ("sac", "sac_paper")
    ]
    # Past MAX_CHECKED_JOBS combinations, each swept value once (the others at their first).
    seen.clear()
    gammas = [0.9, 0.95, 0.99, 0.995, 0.999, 0.9995, 0.9999, 0.99995]
    sweep = ["-m", "seed=range(0,9)", "algo.gamma=" + ",".join(map(str, gammas))]
    check_command_line("train", sweep, seen.append)
    assert len(seen) == 9 + 8
    assert {c.seed for c in seen} == set(range(9))
    assert {c.algo.gamma for c in seen} == set(gammas)
    # --cfg shows a config as it is, values unchecked.
    check_command_line("train", ["--cfg", "job", "seed=-1"], validate_train_config)
    # Hydra's own questions are Hydra's to answer.
    seen.clear()
    check_command_line("train", ["--help"], seen.append)
    assert seen == []
    # A glob over one of conf/'s groups: each of its options, as the sweeper expands it.
    check_command_line("train", ["-m", "drone=glob(attacker_v1*)"], seen.append)
    assert sorted(c.drone.name for c in seen) == [f"attacker_v1{x}" for x in ("", 0, 1, 2, 3, 4)]


def test_the_help_of_evaluate_and_export_lists_only_the_groups_they_take(run_python):
    options = ", ".join(p.stem for p in sorted((CONF_DIR / "dynamics").glob("*.yaml")))
    shown = run_python("evaluate.py", "--help", timeout=120)
    assert shown.returncode == 0, shown.stderr
    groups = shown.stdout.split("== Configuration groups ==")[1].split("== Config ==")[0]
    assert groups.split() == [
        "dynamics:",
        *f"{options} (fly on it instead of the run's own)".split(),
    ]
    assert "run_dir: ???" in shown.stdout
    shown = run_python("export.py", "--help", timeout=120)
    assert shown.returncode == 0, shown.stderr
    assert "== Configuration groups ==" not in shown.stdout and "controller: null" in shown.stdout
