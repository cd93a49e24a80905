"""Aim plays (rlplat.agents.plays) flown plain and through a learner's action, and stored as
demonstrations in the replay buffer (algo.demonstrations)."""

import json

import pytest
import torch

from rlplat import make_env
from rlplat.agents.plays import AimPlay, load_plays
from rlplat.errors import ConfigError
from rlplat.eval.episodes import evaluate

SHORT = "env.time_limit=10"


def random_plays(n: int, parts: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Offsets (n, parts, 1, 3) m and fractions (n, parts, 1) of a lone attacker's plays."""
    g = torch.Generator().manual_seed(seed)
    offset = torch.randn(n, parts, 1, 3, generator=g) * torch.tensor([8.0, 8.0, 3.0])
    fraction = torch.rand(n, parts, 1, generator=g) * 0.6 + 0.4
    return offset, fraction


def fly(env, offset, fraction, through: bool):
    per_part = -(-env.max_steps // offset.shape[1])
    speed = env.scenarios["attacker_max_speed"][:, :1]  # env i flies scenario i
    play = AimPlay(offset, fraction, speed, per_part, 1, env.action_key,
                   env=env if through else None)  # fmt: skip
    return evaluate(env, play, record=True)


def write_plays(path, ids, offset, fraction, split="train", captured=None):
    captured = [True] * len(ids) if captured is None else captured
    doc = {"segments": offset.shape[1], "gain": 2.0, "seed": 0, "split": split, "plays": {
        i: {"captured_at_s": 1.0 if c else None, "least_distance_m": 0.5,
            "offset_m": o.tolist(), "fraction": f.tolist()}
        for i, o, f, c in zip(ids, offset, fraction, captured, strict=True)
    }}  # fmt: skip
    path.write_text(json.dumps(doc))
    return path


@pytest.fixture(scope="module")
def route_flyers(tmp_path_factory, write_small_set):
    """A small set whose defenders all fly their routes: they do not react to the attackers,
    so the attackers' rounding cannot grow through a defender's reaction."""
    path = tmp_path_factory.mktemp("route_flyers")
    return write_small_set(path, "scenario.strategy_mix={setpoints: 1, nn: 0}")


def test_a_play_through_an_ungated_correction_flies_its_plain_command(route_flyers):
    """attacker_v12's action (a correction to the route-intercept law, no gate): the play's
    correction makes the law plus it the plain command, so the drones fly as on action=velocity
    (up to the rounding of subtracting the law and adding it back)."""
    n = len(route_flyers.split("val"))
    offset, fraction = random_plays(n)
    plain = make_env(SHORT, "drone=attacker_v12", "action=velocity", scenarios=route_flyers,
                     split="val", num_envs=n)  # fmt: skip
    law = make_env(SHORT, "drone=attacker_v12", scenarios=route_flyers, split="val", num_envs=n)
    a = fly(plain, offset, fraction, through=False)
    b = fly(law, offset, fraction, through=True)
    assert torch.equal(a.captured, b.captured) and a.captured.any() and not a.captured.all()
    torch.testing.assert_close(b.positions, a.positions, atol=1e-3, rtol=0)


def test_behind_a_shut_gate_a_play_flies_the_law(route_flyers):
    """attacker_v13's action against route flyers, its gate raised above their route
    deviation (it stays under 1.7 m/s^2): the gate stays shut, so whatever the play, the env
    flies the law (a zero correction)."""
    n = len(route_flyers.split("val"))
    shut = ("action.gate_low=4", "action.gate_high=5")
    env = make_env(SHORT, "drone=attacker_v13", *shut, scenarios=route_flyers, split="val",
                   num_envs=n)  # fmt: skip
    offset, fraction = random_plays(n, seed=1)
    played = fly(env, offset, fraction, through=True)
    law = fly(env, torch.zeros_like(offset), torch.zeros_like(fraction), through=False)  # a = 0
    torch.testing.assert_close(played.positions, law.positions, atol=1e-5, rtol=0)
    plain = make_env(SHORT, "action=velocity", scenarios=route_flyers, split="val", num_envs=n)
    assert not torch.allclose(fly(plain, offset, fraction, False).positions, law.positions)


@pytest.mark.parametrize("drone", ["attacker_v12", "attacker_v3"])  # a correction; eq. 2
def test_demonstrations_store_the_plays_that_capture_through_the_action(
    write_small_set, tmp_path, tiny_run, caplog, drone
):
    # attackers within 15 m of the defender, so that 10-s plays capture some
    near = write_small_set(tmp_path / "set", *(f"scenario.params.attacker_d{a}.{e}={s * b}"
                                             for a, b in (("x", 15), ("y", 15), ("z", 5))
                                             for e, s in (("low", -1), ("high", 1))))  # fmt: skip
    ids = near.ids["train"][:24]
    offset, fraction = random_plays(len(ids), seed=2)
    offset[:8], fraction[:8] = 0.0, 1.0  # pure pursuit at full speed
    path = write_plays(tmp_path / "plays.json", ids, offset, fraction)
    # What the run must store: the same plays flown on their scenarios, first episodes.
    first = near.picked("train", torch.arange(len(ids)))
    env = make_env(f"drone={drone}", SHORT, scenarios=first, split="train", num_envs=len(ids))
    flown = fly(env, offset, fraction, through=True)
    captured = flown.captured
    steps = int(flown.length[captured].sum())
    assert 0 < int(captured.sum()) < len(ids)

    with caplog.at_level("INFO", logger="rlplat.experiment.training"):
        tiny_run(near, tmp_path / "run", f"drone={drone}", SHORT,
                 f"algo.demonstrations=[{path}]", "algo.demonstration_repeat=3")  # fmt: skip
    logged = (f"replay buffer: {steps} transitions of the {int(captured.sum())} of {len(ids)} "
              f"plays ({path}) that capture through the action, stored 3 times")  # fmt: skip
    assert logged in caplog.text


def test_plays_that_did_not_capture_in_the_search_are_not_flown(scenarios, tmp_path):
    ids = scenarios.ids["train"][:3]
    offset, fraction = random_plays(3)
    path = write_plays(tmp_path / "p.json", ids, offset, fraction, captured=[True, False, True])
    plays = load_plays(path).capturing()
    assert plays.scenario_ids == [ids[0], ids[2]]
    torch.testing.assert_close(plays.offset, offset[[0, 2]])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algo.demonstrations=[{missing}]"], r"^algo\.demonstrations: no plays file .*ing\.json$"),
        (
            ["algo.demonstrations=[{bad}]"],
            r"^algo\.demonstrations: .*bad\.json is not a plays file",
        ),
        (
            ["algo.demonstrations=[{val}]"],
            r"^algo\.demonstrations: .* holds plays of the val split;",
        ),
        (["algo.demonstrations=[{foreign}]"], r"\(nowhere-1 is not in this train split\)"),
        (
            ["algo.demonstrations=[{plays}]", "drone=defender_v1"],
            r"^algo\.demonstrations: plays fly an attacker, drone\.learner is the defender$",
        ),
        (["algo.demonstration_repeat=0"], r"^algo\.demonstration_repeat: must be"),
    ],
    ids=["missing", "malformed", "other-split", "other-set", "defender", "repeat"],
)
def test_bad_demonstrations_are_refused_before_any_work(
    scenarios, tmp_path, tiny_run, overrides, message
):
    ids = scenarios.ids["train"][:2]
    offset, fraction = random_plays(2)
    files = {
        "missing": tmp_path / "missing.json",
        "bad": tmp_path / "bad.json",
        "val": write_plays(
            tmp_path / "val.json", scenarios.ids["val"][:2], offset, fraction, split="val"
        ),  # fmt: skip
        "foreign": write_plays(tmp_path / "f.json", ["nowhere-1"], offset[:1], fraction[:1]),
        "plays": write_plays(tmp_path / "plays.json", ids, offset, fraction),
    }
    files["bad"].write_text('{"plays": {"x": {}}}')
    with pytest.raises(ConfigError, match=message):
        tiny_run(scenarios, tmp_path / "run", *(o.format(**files) for o in overrides))
    assert not (tmp_path / "run").exists()
