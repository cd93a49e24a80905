import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from rlplat import make_env, make_gym_env
from rlplat.envs.gym import PursuitGymEnv
from rlplat.errors import ConfigError


def test_passes_gymnasium_checker(scenarios):
    env = make_gym_env(scenarios=scenarios.path)
    check_env(env, skip_render_check=True)
    env.close()


def test_paper_api_init_reset_step_close(scenarios):
    env = PursuitGymEnv(make_env("drone=attacker_v1", scenarios=scenarios, split="val"))
    obs, info = env.reset(seed=0)
    assert obs.shape == (12,) and obs.dtype == np.float32
    assert info["scenario_id"] == scenarios.ids["val"][0]
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and reward < 0 and not terminated and not truncated
    assert info["visible"] and info["distance"] > 0
    obs2, info2 = env.reset()
    assert info2["scenario_id"] == scenarios.ids["val"][1]  # the next scenario of the split
    env.close()


def test_any_seed_gymnasium_takes_restarts_the_walk(scenarios):
    # Gymnasium takes any non-negative seed; the walk's generator a 64-bit word of it.
    env = make_gym_env("env.scenario_order=shuffled", scenarios=scenarios.path)

    def walk(seed):
        return [env.reset(seed=seed)[1]["scenario_id"]] + [
            env.reset()[1]["scenario_id"] for _ in range(5)
        ]

    big = walk(2**64 + 7)
    assert big == walk(2**64 + 7) == walk(7)  # the same word: the same walk
    assert walk(2**70 + 1) == walk(2**70 + 1)
    env.close()


def test_step_before_reset_is_refused_as_gymnasium_does(scenarios):
    env = make_gym_env(scenarios=scenarios.path)
    with pytest.raises(gym.error.ResetNeeded, match="before calling env.reset"):
        env.step(env.action_space.sample())
    env.reset(seed=0)
    env.step(env.action_space.sample())  # and steps once reset
    env.close()


def test_step_after_the_episode_ends_needs_a_reset(scenarios):
    env = make_gym_env("env.time_limit=0.5", scenarios=scenarios.path)
    env.reset(seed=0)
    ended = [env.step(np.zeros(3, np.float32))[2:4] for _ in range(5)]
    assert ended == [(False, False)] * 4 + [(False, True)]  # truncated at the time limit
    with pytest.raises(gym.error.ResetNeeded, match="after an episode ends"):
        env.step(np.zeros(3, np.float32))
    env.reset()
    env.step(np.zeros(3, np.float32))
    env.close()


def test_wraps_a_pursuit_env_not_a_transformed_one(scenarios):
    from torchrl.envs import StepCounter, TransformedEnv

    with pytest.raises(ConfigError, match=r"^gym adapter: wraps a PursuitEnv .* TransformedEnv"):
        PursuitGymEnv(TransformedEnv(make_env(scenarios=scenarios), StepCounter()))


def test_wraps_only_a_batch_of_one(scenarios):
    with pytest.raises(ConfigError, match="batch of one env, got num_envs=2"):
        PursuitGymEnv(make_env(scenarios=scenarios, num_envs=2))


@pytest.mark.slow
def test_stable_baselines3_sac_trains_unmodified(scenarios):
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    env = make_gym_env("env.time_limit=5", scenarios=scenarios.path)
    model = SAC("MlpPolicy", env, learning_starts=64, batch_size=32, seed=0, verbose=0)
    model.set_logger(Logger(folder=None, output_formats=[]))  # SB3's own makes a /tmp folder
    model.learn(total_timesteps=200)
    action, _ = model.predict(env.reset(seed=0)[0], deterministic=True)
    assert env.action_space.contains(action)
    assert model.num_timesteps == 200 and model.replay_buffer.size() == 200
    env.close()
