"""The Gymnasium environment: API conformance, episodes, seeding and what the images show."""

import warnings
from collections import Counter

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

from imagine.envs.gesture_puzzle import ENV_ID, GesturePuzzleEnv, rules
from imagine.envs.gesture_puzzle.rules import (
    MAX_EPISODE_ACTIONS,
    TASKS,
    is_terminal,
    rewards,
    transition,
)
from imagine.errors import ConfigError


@pytest.fixture(scope="module")
def env():
    return gym.make(ENV_ID, task="original").unwrapped


@pytest.mark.parametrize("task", rules.TASKS)
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env_passes_without_warnings(task, render_mode):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make(ENV_ID, task=task, render_mode=render_mode).unwrapped)


def test_observation_dtype_shape_and_info(env):
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3)
    assert env.observation_space.contains(obs)
    assert isinstance(info["macrostate"], tuple) and len(info["macrostate"]) == 4
    for _ in range(5):
        obs, _, term, trunc, info = env.step(env.action_space.sample())
        assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3)
        assert info["macrostate"] == env.macrostate
        if term or trunc:
            break


def test_same_seed_same_episode_other_seed_other_episode():
    def rollout(seed):
        e = GesturePuzzleEnv(task="hard")
        obs, info = e.reset(seed=seed)
        frames, states = [obs], [info["macrostate"]]
        for a in [0, 3, 4, 1, 5, 2]:
            obs, _, term, trunc, info = e.step(a)
            frames.append(obs)
            states.append(info["macrostate"])
            if term or trunc:
                break
        return np.stack(frames), states

    a, b, c = rollout(7), rollout(7), rollout(8)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    assert not np.array_equal(a[0][0], c[0][0])


@pytest.mark.parametrize("task", rules.TASKS)
def test_reset_is_uniform_over_legal_non_goal_states(task):
    e = GesturePuzzleEnv(task=task)
    e.reset(seed=1)
    starts = {tuple(int(x) for x in s) for s in rules.start_states(task)}
    n = 60 * len(starts)
    counts = Counter(e.reset()[1]["macrostate"] for _ in range(n))
    assert set(counts) == starts  # only legal non-goal states, and every one of them
    # Uniform: each of the k states is hit about n/k = 60 times (chi-square, 1e-4 level).
    expected = n / len(starts)
    chi2 = sum((c - expected) ** 2 / expected for c in counts.values())
    assert chi2 < len(starts) + 5 * np.sqrt(2 * len(starts))


def test_episode_rewards_and_termination():
    e = GesturePuzzleEnv(task="original")
    _, info = e.reset(seed=0, options={"macrostate": (1, 0, 3, 0)})  # RIGHT UP LEFT, hand 0
    assert info["macrostate"] == (1, 0, 3, 0)
    _, r, term, trunc, info = e.step(0)  # cube 0 clockwise: DOWN -> goal
    assert (r, term, trunc, info["macrostate"]) == (50.0, True, False, (2, 0, 3, 0))
    e.reset(options={"macrostate": (1, 0, 3, 0)})
    _, r, term, trunc, _ = e.step(1)  # cube 0 counter-clockwise: UP, shared with cube 1
    assert (r, term, trunc) == (-5.0, True, False)
    e.reset(options={"macrostate": (1, 0, 3, 0)})
    _, r, term, trunc, _ = e.step(3)  # cube 1 counter-clockwise: LEFT, shared with cube 2
    assert (r, term, trunc) == (-5.0, True, False)


def test_truncation_after_ten_actions_and_hand_never_moves():
    e = GesturePuzzleEnv(task="original")
    # (UP, RIGHT, LEFT, 2) with DOWN free: cube 1 RIGHT -> DOWN and back is always legal and
    # never a goal (the hand points at cube 2, which stays LEFT).
    e.reset(seed=0, options={"macrostate": (0, 1, 3, 2)})
    for t in range(1, 11):
        _, r, term, trunc, info = e.step(2 if t % 2 else 3)
        assert r == -1.0 and not term
        assert trunc == (t == 10)
        assert info["macrostate"][3] == 2 and info["actions"] == t


def test_invalid_actions_raise_clear_errors(env):
    env.reset(seed=0)
    for bad in (6, -1, 2.5, "1", None):
        with pytest.raises(ValueError, match="invalid action"):
            env.step(bad)
    env.step(np.int64(3))  # numpy integers are fine


def test_bad_arguments():
    with pytest.raises(ConfigError, match="unknown task 'easy'"):
        GesturePuzzleEnv(task="easy")
    with pytest.raises(ConfigError, match="render_mode"):
        GesturePuzzleEnv(render_mode="human")
    e = GesturePuzzleEnv()
    with pytest.raises(ValueError, match="terminal"):
        e.reset(options={"macrostate": (0, 0, 1, 0)})
    with pytest.raises(ValueError, match="out of range"):
        e.reset(options={"macrostate": (0, 4, 1, 0)})


def test_render_returns_the_full_scene_the_observation_is_cut_from():
    from imagine.envs.gesture_puzzle.scene import area_resize_matrix

    e = GesturePuzzleEnv(render_mode="rgb_array")
    obs, _ = e.reset(seed=3)
    frame = e.render()
    assert frame.dtype == np.uint8 and frame.shape == (144, 288, 3)
    assert (frame[..., 0] == frame[..., 2]).all()  # a grayscale scene
    rows, cols = area_resize_matrix(144, 64), area_resize_matrix(96, 64).T
    scene = frame[..., 0].astype(np.float64)
    for i in range(3):  # three strips along the horizontal axis, each resized to 64 x 64
        strip = rows @ scene[:, 96 * i : 96 * (i + 1)] @ cols
        assert np.abs(strip - obs[..., i]).max() <= 1.0
    assert GesturePuzzleEnv().render() is None


def _linear_probe_accuracy(x, labels, n_fit):
    """Fit a ridge-regression classifier on the first ``n_fit`` rows; accuracy on the rest."""
    x = (x - x.mean(1, keepdims=True)) / x.std(1, keepdims=True)  # contrast-normalize
    x = np.c_[x, np.ones(len(x))]
    targets = np.eye(labels.max() + 1)[labels]
    a, t = x[:n_fit], targets[:n_fit]
    w = np.linalg.solve(a.T @ a + np.eye(a.shape[1]), a.T @ t)
    return float(((x[n_fit:] @ w).argmax(1) == labels[n_fit:]).mean())


def test_arrows_and_pointed_cube_are_readable_from_the_observation():
    """Each channel shows one cube's arrow, and the hand shows in the pointed cube's channel:
    a linear probe on the pixels of a channel, at half resolution, reads them."""
    from imagine.envs.gesture_puzzle import make_composer

    composer = make_composer()
    rng = np.random.default_rng(0)
    states = rules.all_macrostates()[rng.integers(0, 192, 4000)]
    obs = composer.sample(rng, states).astype(np.float64) / 255
    half = obs.reshape(len(obs), 32, 2, 32, 2, 3).mean(axis=(2, 4))
    for cube in range(3):
        x = half[:, :20, :, cube].reshape(len(obs), -1)  # the cube part of the strip
        acc = _linear_probe_accuracy(x, states[:, cube], n_fit=3000)
        assert acc > 0.99, f"arrow of cube {cube}: {acc:.3f}"
    x = half[:, 22:, :, :].reshape(len(obs), -1)  # the hand part of all three strips
    acc = _linear_probe_accuracy(x, states[:, 3], n_fit=3000)
    assert acc > 0.99, f"pointed cube: {acc:.3f}"


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    actions=st.lists(st.integers(0, 5), min_size=1, max_size=40),
    task=st.sampled_from(TASKS),
)
def test_any_action_sequence_keeps_the_environment_consistent(seed, actions, task):
    """Episodes restart from legal non-goal states, every reward matches the state entered,
    an episode ends exactly on goal or illegal states or after 10 actions, and the hand never
    moves within an episode."""
    env = GesturePuzzleEnv(task=task)
    obs, info = env.reset(seed=seed)
    state, length = tuple(info["macrostate"]), 0
    for action in actions:
        assert not is_terminal(np.array(state), task)
        obs, reward, terminated, truncated, info = env.step(action)
        nxt = tuple(info["macrostate"])
        length += 1
        assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8
        assert nxt == transition(state, action) and nxt[3] == state[3]
        assert reward == float(rewards(np.array(nxt), task))
        assert terminated == bool(is_terminal(np.array(nxt), task))
        assert truncated == (not terminated and length == MAX_EPISODE_ACTIONS)
        state = nxt
        if terminated or truncated:
            obs, info = env.reset()
            state, length = tuple(info["macrostate"]), 0


def test_importing_the_package_registers_the_environment():
    """`import imagine` is enough for gymnasium.make; the env's modules load on make."""
    import subprocess
    import sys

    code = (
        "import sys, gymnasium, imagine\n"
        "assert 'imagine.envs.gesture_puzzle' not in sys.modules\n"
        "env = gymnasium.make('imagine/GesturePuzzle-v0', task='hard')\n"
        "print(env.reset(seed=0)[0].shape)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "(64, 64, 3)"


# --- The stochastic human (issue 16) ------------------------------------------------------------


def independent_next_states(state, action, p):
    """The next-state distribution from the task's definition, written apart from rules.py:
    cube a // 2 turns clockwise (a even) or back; then the hand stays (1 - p) or moves to each
    other cube (p / 2)."""
    d = list(state[:3])
    d[action // 2] = (d[action // 2] + (1 if action % 2 == 0 else 3)) % 4
    out = Counter()
    for hand in range(3):
        chance = 1 - p if hand == state[3] else p / 2
        if chance > 0:
            out[(*d, hand)] += chance
    return dict(out)


@pytest.mark.parametrize("p", [0.0, 0.1, 0.3])
def test_the_stochastic_humans_distribution_is_the_rules(p):
    """rules.next_state_distribution over all 192 x 6 transitions, against the definition."""
    for state in rules.all_macrostates():
        state = tuple(int(x) for x in state)
        for action in range(6):
            exact = rules.next_state_distribution(state, action, p)
            expected = independent_next_states(state, action, p)
            assert exact.keys() == expected.keys(), (state, action)
            assert all(abs(exact[k] - expected[k]) < 1e-12 for k in exact), (state, action)
            assert abs(sum(exact.values()) - 1) < 1e-12


@pytest.mark.parametrize("task", rules.TASKS)
def test_the_environment_draws_the_stochastic_humans_distribution(task):
    """6000 environments, each from the same start, one action: the observed next macrostates
    follow the exact distribution (each frequency within 4.5 standard errors), rewards and
    ends follow the state after the hand moved."""
    from gymnasium.vector import AutoresetMode

    from imagine.envs.gesture_puzzle import GesturePuzzleVectorEnv

    n, p = 6000, 0.3
    envs = GesturePuzzleVectorEnv(n, task=task, hand_switch_prob=p,
                                  autoreset_mode=AutoresetMode.DISABLED)  # fmt: skip
    start = tuple(int(x) for x in rules.start_states(task)[5])
    for action in (0, 3):
        envs.reset(seed=action, options={"macrostates": np.array([start] * n)})
        _, reward, terminated, _, info = envs.step(np.full(n, action))
        seen = Counter(tuple(int(x) for x in s) for s in info["macrostate"])
        exact = rules.next_state_distribution(start, action, p)
        assert seen.keys() == exact.keys()
        for state, chance in exact.items():
            error = (chance * (1 - chance) / n) ** 0.5
            assert abs(seen[state] / n - chance) < 4.5 * error, (state, seen[state], chance)
        np.testing.assert_array_equal(reward, rules.rewards(info["macrostate"], task))
        np.testing.assert_array_equal(terminated, rules.is_terminal(info["macrostate"], task))


@pytest.mark.parametrize(("task", "p"), [("hard", 0.0), ("hard", 0.3), ("original", 0.3)])
def test_best_success_is_what_its_policy_reaches_in_the_environment(task, p):
    """best_success's policy, run in 3000 environments (each its own start and hand draws),
    succeeds as often as its dynamic program says (within 4 standard errors); every start is
    solvable without a stochastic human, and a stochastic human costs success."""
    from gymnasium.vector import AutoresetMode

    from imagine.envs.gesture_puzzle import GesturePuzzleVectorEnv

    best, actions = rules.best_success(task, p)
    n = 3000
    envs = GesturePuzzleVectorEnv(n, task=task, hand_switch_prob=p,
                                  autoreset_mode=AutoresetMode.SAME_STEP)  # fmt: skip
    _, info = envs.reset(seed=11)
    running, success = np.ones(n, dtype=bool), np.zeros(n, dtype=bool)
    while running.any():
        left = rules.MAX_EPISODE_ACTIONS - info["actions"]
        chosen = actions[left - 1, rules.macrostate_index(info["macrostate"])]
        _, reward, terminated, truncated, info = envs.step(chosen)
        success |= running & (reward == rules.REWARD_GOAL)
        running &= ~(terminated | truncated)
    error = max(best * (1 - best) / n, 1 / n**2) ** 0.5
    assert abs(success.mean() - best) < 4 * error, (success.mean(), best)
    assert (best == 1.0) if p == 0 else (0.8 < best < 1.0)


def test_check_env_passes_with_a_stochastic_human():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make(ENV_ID, task="hard", hand_switch_prob=0.3).unwrapped)


def test_a_hand_switch_prob_must_be_a_probability():
    for bad in (-0.1, 1.5, "often"):
        with pytest.raises(ConfigError, match="hand_switch_prob"):
            GesturePuzzleEnv(hand_switch_prob=bad)
