"""GesturePuzzleVectorEnv: one batch that behaves exactly like N single environments."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from imagine.envs.gesture_puzzle import ENV_ID, GesturePuzzleEnv, GesturePuzzleVectorEnv, rules
from imagine.errors import ConfigError

TASKS = ("original", "hard")
MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)


def make_vector(num_envs: int, task: str, **kwargs) -> GesturePuzzleVectorEnv:
    env = gym.make_vec(
        ENV_ID, num_envs=num_envs, task=task, vectorization_mode="vector_entry_point", **kwargs
    )
    assert isinstance(env, GesturePuzzleVectorEnv)
    return env


def make_sync(num_envs: int, task: str, mode: AutoresetMode, **kwargs) -> SyncVectorEnv:
    return SyncVectorEnv(
        [lambda: gym.make(ENV_ID, task=task, **kwargs) for _ in range(num_envs)],
        autoreset_mode=mode,
    )


def macrostates(info_value) -> np.ndarray:
    """SyncVectorEnv batches the single env's tuple macrostates as an object array."""
    return np.array([tuple(m) for m in info_value], dtype=np.int64)


def safe_ping_pong(task: str) -> tuple[np.ndarray, int]:
    """A start state and a cube (not the pointed one) such that rotating that cube clockwise
    and back never enters a terminal state: episodes driven this way can only truncate."""
    for state in rules.start_states(task):
        for cube in range(rules.N_CUBES):
            if cube == state[3]:
                continue
            turned = rules.apply_actions(state, np.int64(2 * cube))
            back = rules.apply_actions(turned, np.int64(2 * cube + 1))
            if not rules.is_terminal(turned, task) and np.array_equal(back, state):
                return np.array(state), cube
    raise AssertionError(f"no safe ping-pong in task {task}")


# --- Construction ------------------------------------------------------------------------------


@pytest.mark.parametrize("task", TASKS)
def test_make_vec_builds_the_vector_env(task: str) -> None:
    env = make_vector(7, task)
    assert env.num_envs == 7
    assert env.task == task
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert env.single_observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.single_action_space == gym.spaces.Discrete(6)
    assert env.observation_space.shape == (7, 64, 64, 3)
    obs, info = env.reset(seed=0)
    assert obs.shape == (7, 64, 64, 3) and obs.dtype == np.uint8
    assert env.observation_space.contains(obs)
    assert info["macrostate"].shape == (7, 4) and info["macrostate"].dtype == np.int64
    np.testing.assert_array_equal(info["actions"], np.zeros(7))
    assert not rules.is_terminal(info["macrostate"], task).any()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"num_envs": 0},
        {"num_envs": -3},
        {"num_envs": 2.0},
        {"num_envs": 2, "task": "bogus"},
        {"num_envs": 2, "render_mode": "human"},
        {"num_envs": 2, "autoreset_mode": "sometimes"},
    ],
    ids=lambda kw: "-".join(f"{k}={v}" for k, v in kw.items()),
)
def test_bad_constructor_arguments_raise_config_error(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        GesturePuzzleVectorEnv(**kwargs)


def test_make_vec_with_a_bad_task_raises_config_error() -> None:
    with pytest.raises(ConfigError, match="bogus"):
        gym.make_vec(ENV_ID, num_envs=2, task="bogus", vectorization_mode="vector_entry_point")
    with pytest.raises(ConfigError, match="num_envs"):
        gym.make_vec(ENV_ID, num_envs=0, vectorization_mode="vector_entry_point")


# --- Step for step the same as N single environments --------------------------------------


@pytest.mark.parametrize("p", [0.0, 0.3], ids=["paper", "stochastic-human"])
@pytest.mark.parametrize("mode", MODES, ids=lambda m: m.value)
@pytest.mark.parametrize("task", TASKS)
def test_matches_sync_vector_env_step_for_step(task: str, mode: AutoresetMode, p: float) -> None:
    n = 5
    vec = make_vector(n, task, autoreset_mode=mode, hand_switch_prob=p)
    sync = make_sync(n, task, mode, hand_switch_prob=p)
    obs_v, info_v = vec.reset(seed=123)
    obs_s, info_s = sync.reset(seed=123)
    np.testing.assert_array_equal(obs_v, obs_s)
    np.testing.assert_array_equal(info_v["macrostate"], macrostates(info_s["macrostate"]))

    rng = np.random.default_rng(7)
    episodes_ended = 0
    for t in range(100):
        actions = rng.integers(0, 6, size=n)
        obs_v, rew_v, term_v, trunc_v, info_v = vec.step(actions)
        obs_s, rew_s, term_s, trunc_s, info_s = sync.step(actions)
        where = f"task {task}, {mode.value}, step {t}"
        np.testing.assert_array_equal(obs_v, obs_s, err_msg=where)
        np.testing.assert_array_equal(rew_v, rew_s, err_msg=where)
        np.testing.assert_array_equal(term_v, term_s, err_msg=where)
        np.testing.assert_array_equal(trunc_v, trunc_s, err_msg=where)
        np.testing.assert_array_equal(
            info_v["macrostate"], macrostates(info_s["macrostate"]), err_msg=where
        )
        np.testing.assert_array_equal(info_v["actions"], info_s["actions"], err_msg=where)
        assert obs_v.dtype == np.uint8 and rew_v.dtype == np.float64
        assert term_v.dtype == trunc_v.dtype == np.bool_
        if mode == AutoresetMode.SAME_STEP:
            done = term_s | trunc_s
            np.testing.assert_array_equal(info_v["_final_obs"], done, err_msg=where)
            for i in np.flatnonzero(done):
                np.testing.assert_array_equal(info_v["final_obs"][i], info_s["final_obs"][i])
                assert tuple(info_v["final_macrostate"][i]) == info_s["final_info"]["macrostate"][i]
        episodes_ended += int((term_v | trunc_v).sum())
    # Random play ends episodes often: the comparison covered many autoresets.
    assert episodes_ended >= 20


def test_reset_with_a_list_of_seeds_matches_single_envs() -> None:
    # Reseeding with a list of seeds (one per sub-env) is the same as seeding each single env.
    n = 3
    vec = make_vector(n, "hard")
    singles = [GesturePuzzleEnv(task="hard") for _ in range(n)]
    seeds = [11, 5, 99]
    obs_v, info_v = vec.reset(seed=seeds)
    for i, (env, seed) in enumerate(zip(singles, seeds, strict=True)):
        obs, info = env.reset(seed=seed)
        np.testing.assert_array_equal(obs_v[i], obs)
        assert tuple(info_v["macrostate"][i]) == info["macrostate"]
    with pytest.raises(ValueError, match="seeds"):
        vec.reset(seed=[1, 2])


# --- Autoreset --------------------------------------------------------------------------------


@pytest.mark.parametrize("task", TASKS)
def test_same_step_autoreset_returns_a_fresh_start(task: str) -> None:
    n = 8
    env = make_vector(n, task, autoreset_mode=AutoresetMode.SAME_STEP)
    obs, info = env.reset(seed=0)
    starts = {tuple(s) for s in rules.start_states(task)}
    taken = np.zeros(n, dtype=np.int64)  # actions taken in each current episode, counted here
    rng = np.random.default_rng(1)
    ended = 0
    for _ in range(80):
        before = info["macrostate"]
        actions = rng.integers(0, 6, size=n)
        obs, reward, terminated, truncated, info = env.step(actions)
        taken += 1
        done = terminated | truncated
        assert not (terminated & truncated).any()
        np.testing.assert_array_equal(info["_final_obs"], done)
        final = info["final_macrostate"]
        # The final macrostate is where the actions led, and the reward is that state's.
        np.testing.assert_array_equal(final, rules.apply_actions(before, actions))
        np.testing.assert_array_equal(reward, rules.rewards(final, task))
        np.testing.assert_array_equal(terminated, rules.is_terminal(final, task))
        np.testing.assert_array_equal(truncated, ~terminated & (taken == 10))
        for i in np.flatnonzero(done):
            assert rules.is_terminal(final[i], task) or taken[i] == 10
            assert tuple(info["macrostate"][i]) in starts  # legal, not a goal
            assert info["actions"][i] == 0
        for i in np.flatnonzero(~done):
            np.testing.assert_array_equal(info["macrostate"][i], final[i])
            assert info["actions"][i] == taken[i]
            np.testing.assert_array_equal(info["final_obs"][i], obs[i])
        taken[done] = 0
        ended += int(done.sum())
    assert ended >= 20


@pytest.mark.parametrize("task", TASKS)
def test_next_step_autoreset_ignores_the_action_after_an_episode_ends(task: str) -> None:
    n = 6
    env = make_vector(n, task)
    _, info = env.reset(seed=3)
    rng = np.random.default_rng(2)
    pending = np.zeros(n, dtype=bool)
    starts = {tuple(s) for s in rules.start_states(task)}
    resets = 0
    for _ in range(60):
        before = info["macrostate"]
        actions = rng.integers(0, 6, size=n)
        _, reward, terminated, truncated, info = env.step(actions)
        for i in np.flatnonzero(pending):
            assert reward[i] == 0.0 and not terminated[i] and not truncated[i]
            assert info["actions"][i] == 0
            assert tuple(info["macrostate"][i]) in starts
        stepped = ~pending
        np.testing.assert_array_equal(
            info["macrostate"][stepped], rules.apply_actions(before[stepped], actions[stepped])
        )
        resets += int(pending.sum())
        pending = terminated | truncated
    assert resets >= 10


@pytest.mark.parametrize("mode", MODES, ids=lambda m: m.value)
@pytest.mark.parametrize("task", TASKS)
def test_truncation_after_ten_actions(task: str, mode: AutoresetMode) -> None:
    state, cube = safe_ping_pong(task)
    n = 3
    env = make_vector(n, task, autoreset_mode=mode)
    env.reset(seed=0, options={"macrostates": np.tile(state, (n, 1))})
    for t in range(1, 11):
        actions = np.full(n, 2 * cube + (t + 1) % 2)  # clockwise, then back, ...
        _, reward, terminated, truncated, info = env.step(actions)
        np.testing.assert_array_equal(reward, np.full(n, rules.REWARD_STEP))
        assert not terminated.any()
        np.testing.assert_array_equal(truncated, np.full(n, t == 10))
        if t < 10:
            np.testing.assert_array_equal(info["actions"], np.full(n, t))
    final = info["final_macrostate"] if mode == AutoresetMode.SAME_STEP else info["macrostate"]
    np.testing.assert_array_equal(final, np.tile(state, (n, 1)))  # an even number of turns

    if mode == AutoresetMode.SAME_STEP:
        np.testing.assert_array_equal(info["actions"], np.zeros(n))
        assert info["_final_obs"].all()
    else:
        # The step after the truncation resets: no reward, action ignored, a new episode.
        _, reward, terminated, truncated, info = env.step(np.full(n, 2 * cube))
        np.testing.assert_array_equal(reward, np.zeros(n))
        assert not terminated.any() and not truncated.any()
        np.testing.assert_array_equal(info["actions"], np.zeros(n))
    # The new episodes run normally.
    _, reward, terminated, truncated, info = env.step(np.zeros(n, dtype=np.int64))
    assert (reward != 0).all() and not truncated.any()
    ended_again = terminated if mode == AutoresetMode.SAME_STEP else np.zeros(n, dtype=bool)
    np.testing.assert_array_equal(info["actions"], np.where(ended_again, 0, 1))


def test_single_env_truncates_the_same_way() -> None:
    state, cube = safe_ping_pong("original")
    env = GesturePuzzleEnv(task="original")
    env.reset(seed=0, options={"macrostate": tuple(state)})
    for t in range(1, 11):
        _, _, terminated, truncated, info = env.step(2 * cube + (t + 1) % 2)
        assert not terminated and truncated == (t == 10)
        assert info["actions"] == t


# --- reset options ----------------------------------------------------------------------------


def test_reset_from_given_macrostates() -> None:
    starts = rules.start_states("hard")
    chosen = starts[[0, 17, 65, 30]]
    env = make_vector(4, "hard")
    obs, info = env.reset(seed=0, options={"macrostates": chosen})
    np.testing.assert_array_equal(info["macrostate"], chosen)
    np.testing.assert_array_equal(info["actions"], np.zeros(4))
    # The observation is drawn from the given state: the same as a single env started there.
    for i in range(4):
        single = GesturePuzzleEnv(task="hard")
        obs_i, _ = single.reset(seed=i, options={"macrostate": tuple(chosen[i])})
        np.testing.assert_array_equal(obs[i], obs_i)
    # Lists work too, and stepping goes on from those states.
    _, info = env.reset(options={"macrostates": chosen.tolist()})
    _, _, _, _, info = env.step(np.array([0, 1, 2, 3]))
    np.testing.assert_array_equal(info["macrostate"], rules.apply_actions(chosen, [0, 1, 2, 3]))


@pytest.mark.parametrize(
    ("states", "match"),
    [
        (np.zeros((3, 4), dtype=np.int64), "shape"),  # 3 states for 4 envs
        (np.ones(4, dtype=np.int64), "shape"),
        (np.array([[0, 1, 2, 0], [0, 1, 3, 0], [0, 2, 2, 0], [0, 1, 3, 1]]), "terminal"),
        (np.array([[0, 1, 3, 0], [0, 1, 4, 0], [0, 1, 3, 0], [0, 1, 3, 0]]), "out of range"),
        (np.array([[0, 1, 3, 0], [0, 1, 3, 3], [0, 1, 3, 0], [0, 1, 3, 0]]), "out of range"),
        (np.full((4, 4), 0.5), "4 integers"),
    ],
    ids=["too-few", "flat", "terminal", "direction-4", "hand-3", "floats"],
)
def test_reset_rejects_bad_macrostates(states: np.ndarray, match: str) -> None:
    env = make_vector(4, "original")
    with pytest.raises(ValueError, match=match):
        env.reset(options={"macrostates": states})


def test_reset_mask_resets_only_some() -> None:
    n = 4
    env = make_vector(n, "original")
    state, cube = safe_ping_pong("original")
    env.reset(seed=0, options={"macrostates": np.tile(state, (n, 1))})
    obs, _, _, _, info = env.step(np.full(n, 2 * cube))
    moved = info["macrostate"].copy()
    np.testing.assert_array_equal(info["actions"], np.ones(n))

    mask = np.array([True, False, True, False])
    other = rules.start_states("original")[[5, 9, 12, 40]]
    obs2, info2 = env.reset(seed=50, options={"reset_mask": mask, "macrostates": other})
    np.testing.assert_array_equal(info2["macrostate"][mask], other[mask])
    np.testing.assert_array_equal(info2["macrostate"][~mask], moved[~mask])
    np.testing.assert_array_equal(info2["actions"], [0, 1, 0, 1])
    np.testing.assert_array_equal(obs2[~mask], obs[~mask])  # untouched: same fragments

    # A mask without macrostates draws fresh starts for the masked envs only.
    obs3, info3 = env.reset(options={"reset_mask": ~mask})
    np.testing.assert_array_equal(info3["macrostate"][mask], other[mask])
    np.testing.assert_array_equal(info3["actions"], [0, 0, 0, 0])
    np.testing.assert_array_equal(obs3[mask], obs2[mask])
    assert not rules.is_terminal(info3["macrostate"], "original").any()

    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.array([1, 0, 1, 0])})
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.array([True, False])})


def test_reset_mask_clears_a_pending_autoreset() -> None:
    n = 2
    env = make_vector(n, "original")
    # Cube 0 one turn from sharing cube 1's direction: the first action is illegal.
    start = next(s for s in rules.start_states("original") if s[0] == (s[1] + 1) % 4)
    env.reset(seed=0, options={"macrostates": np.tile(start, (n, 1))})
    _, reward, terminated, _, _ = env.step(np.array([1, 1]))  # cube 0 counter-clockwise
    assert terminated.all() and (reward == rules.REWARD_ILLEGAL).all()
    env.reset(options={"reset_mask": np.array([True, False]), "macrostates": [start, start]})
    _, reward, _, _, info = env.step(np.array([0, 0]))
    assert reward[0] != 0 and info["actions"][0] == 1  # env 0 steps: its reset was done
    assert reward[1] == 0 and info["actions"][1] == 0  # env 1 autoresets, ignoring its action


# --- Invalid actions --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "actions",
    [
        np.array([0, 1, 6]),
        np.array([-1, 0, 0]),
        np.array([0, 1]),
        np.array([0, 1, 2, 3]),
        np.array([[0, 1, 2]]),
        np.int64(1),
        np.array([0.0, 1.0, 2.0]),
        [0, 1.5, 2],
        np.array([True, False, True]),
        "012",
    ],
    ids=[
        "too-large",
        "negative",
        "too-few",
        "too-many",
        "2d",
        "scalar",
        "float-array",
        "float-list",
        "bool",
        "string",
    ],
)
def test_invalid_actions_raise_value_error(actions) -> None:
    env = make_vector(3, "original")
    _, info = env.reset(seed=0)
    before = info["macrostate"]
    with pytest.raises(ValueError):
        env.step(actions)
    # Nothing moved: a valid step afterwards counts one action.
    _, _, _, _, info = env.step([0, 0, 0])
    np.testing.assert_array_equal(info["actions"], np.ones(3))
    np.testing.assert_array_equal(info["macrostate"], rules.apply_actions(before, [0, 0, 0]))


def test_actions_as_a_list_of_ints_are_accepted() -> None:
    env = make_vector(3, "original")
    env.reset(seed=0)
    obs, *_ = env.step([5, 4, 3])
    assert obs.shape == (3, 64, 64, 3)


# --- Rendering --------------------------------------------------------------------------------


def test_render_returns_the_full_scenes() -> None:
    env = make_vector(2, "original", render_mode="rgb_array")
    env.reset(seed=0)
    frames = env.render()
    assert len(frames) == 2
    for frame in frames:
        assert frame.shape == (144, 288, 3) and frame.dtype == np.uint8
        np.testing.assert_array_equal(frame[..., 0], frame[..., 1])
    assert make_vector(2, "original").render() is None


def test_disabled_autoreset_resets_only_what_is_asked() -> None:
    envs = GesturePuzzleVectorEnv(3, autoreset_mode=AutoresetMode.DISABLED)
    _, info = envs.reset(seed=[5, 6, 7])
    ended = np.zeros(3, dtype=bool)
    for _ in range(rules.MAX_EPISODE_ACTIONS + 3):  # past every episode's end
        _, _, terminated, truncated, info = envs.step(np.zeros(3, dtype=np.int64))
        assert not (ended & (terminated | truncated)).any()  # an ended episode ends once
        ended |= terminated | truncated
    assert ended.all()
    lengths = info["actions"].copy()
    assert (lengths >= 1).all() and (lengths <= rules.MAX_EPISODE_ACTIONS).all()
    mask = np.array([True, False, False])
    obs, info = envs.reset(options={"reset_mask": mask})
    assert info["actions"].tolist() == [0, *lengths[1:]]
    held = obs[1:].copy()
    obs, reward, *_, info = envs.step(np.zeros(3, dtype=np.int64))  # the reset one runs again
    assert info["actions"].tolist() == [1, *lengths[1:]]
    np.testing.assert_array_equal(obs[1:], held)
    assert (reward[1:] == 0.0).all() and reward[0] != 0.0


@pytest.mark.parametrize("p", [0.0, 0.3], ids=["paper", "stochastic-human"])
def test_disabled_autoreset_runs_each_episode_as_a_single_env_then_holds_it(p: float) -> None:
    """Until its episode ends a sub-environment is its single environment step for step; after
    that it is not stepped: observation and macrostate held, reward 0, no second end, no draw
    from its generator."""
    n = 6
    vec = GesturePuzzleVectorEnv(n, task="hard", autoreset_mode=AutoresetMode.DISABLED,
                                 hand_switch_prob=p)  # fmt: skip
    singles = [gym.make(ENV_ID, task="hard", hand_switch_prob=p) for _ in range(n)]
    obs_v, _ = vec.reset(seed=123)
    for i, env in enumerate(singles):
        obs_i, _ = env.reset(seed=123 + i)
        np.testing.assert_array_equal(obs_v[i], obs_i)
    rng = np.random.default_rng(7)
    running = np.ones(n, dtype=bool)
    held: dict[int, tuple] = {}
    for t in range(rules.MAX_EPISODE_ACTIONS + 2):
        actions = rng.integers(0, 6, size=n)
        obs_v, rew_v, term_v, trunc_v, info_v = vec.step(actions)
        for i in range(n):
            if running[i]:
                obs_i, rew_i, term_i, trunc_i, info_i = singles[i].step(int(actions[i]))
                np.testing.assert_array_equal(obs_v[i], obs_i, err_msg=f"env {i}, step {t}")
                assert (rew_v[i], term_v[i], trunc_v[i]) == (rew_i, term_i, trunc_i)
                assert tuple(info_v["macrostate"][i]) == tuple(info_i["macrostate"])
                if term_i or trunc_i:
                    running[i] = False
                    held[i] = (obs_v[i].copy(), info_v["macrostate"][i].copy(),
                               vec._rng(i).bit_generator.state)  # fmt: skip
            else:
                obs, state, generator = held[i]
                np.testing.assert_array_equal(obs_v[i], obs)
                np.testing.assert_array_equal(info_v["macrostate"][i], state)
                assert (rew_v[i], term_v[i], trunc_v[i]) == (0.0, False, False)
                assert vec._rng(i).bit_generator.state == generator
    assert not running.any()
