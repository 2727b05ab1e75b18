"""The GesturePuzzle state machine against docs/design.md section 1, case by case."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from imagine.envs.gesture_puzzle import rules
from imagine.envs.gesture_puzzle.rules import DOWN, LEFT, RIGHT, UP


def goal(state, task):
    return bool(rules.is_goal(np.array(state), task))


def illegal(state):
    return bool(rules.is_illegal(np.array(state)))


def test_counts():
    s = rules.all_macrostates()
    assert s.shape == (192, 4)
    assert len({tuple(x) for x in s}) == 192
    assert (rules.macrostate_index(s) == np.arange(192)).all()
    assert int(rules.is_illegal(s).sum()) == 192 - 72  # 24 arrow triples with distinct arrows x 3
    assert int(rules.is_goal(s, "original").sum()) == 18
    assert int(rules.is_goal(s, "hard").sum()) == 6
    assert len(rules.start_states("original")) == 54
    assert len(rules.start_states("hard")) == 66


@pytest.mark.parametrize(
    "state",
    [(UP, UP, DOWN, 0), (RIGHT, LEFT, RIGHT, 1), (DOWN, LEFT, LEFT, 2), (UP, UP, UP, 0)],
)
def test_two_arrows_sharing_a_direction_is_illegal(state):
    assert illegal(state)
    assert not goal(state, "original") and not goal(state, "hard")


@pytest.mark.parametrize(
    "state, original, hard",
    [
        ((DOWN, UP, RIGHT, 0), True, False),  # pointed cube faces the human; an arrow is UP
        ((LEFT, DOWN, RIGHT, 1), True, True),  # no arrow faces the robot
        ((RIGHT, LEFT, DOWN, 2), True, True),
        ((UP, LEFT, DOWN, 2), True, False),
        ((DOWN, LEFT, RIGHT, 1), False, False),  # a DOWN arrow, but not on the pointed cube
        ((LEFT, RIGHT, UP, 0), False, False),
    ],
)
def test_goal_for_both_tasks(state, original, hard):
    assert not illegal(state)
    assert goal(state, "original") is original
    assert goal(state, "hard") is hard


def test_rotation_both_ways_and_hand_never_moves():
    s = (UP, RIGHT, DOWN, 1)
    assert rules.transition(s, 0) == (RIGHT, RIGHT, DOWN, 1)  # cube 0 clockwise
    assert rules.transition(s, 1) == (LEFT, RIGHT, DOWN, 1)  # cube 0 counter-clockwise
    assert rules.transition(s, 2) == (UP, DOWN, DOWN, 1)
    assert rules.transition(s, 3) == (UP, UP, DOWN, 1)
    assert rules.transition(s, 4) == (UP, RIGHT, LEFT, 1)
    assert rules.transition(s, 5) == (UP, RIGHT, RIGHT, 1)
    for state in rules.all_macrostates():
        for a in range(6):
            nxt = rules.transition(tuple(state), a)
            assert nxt[3] == state[3]
            assert rules.transition(nxt, a ^ 1) == tuple(state)  # the other way undoes it
            assert rules.transition(rules.transition(rules.transition(nxt, a), a), a) == tuple(
                state
            )  # four quarter turns


def test_rewards():
    states = np.array([(LEFT, DOWN, RIGHT, 1), (UP, UP, DOWN, 0), (UP, RIGHT, DOWN, 0)])
    assert rules.rewards(states, "original").tolist() == [50.0, -5.0, -1.0]
    # An original-task goal with an UP arrow is an ordinary step in the hard task.
    assert rules.rewards(np.array([(DOWN, UP, RIGHT, 0)]), "hard").tolist() == [-1.0]


def test_vectorized_rules_match_tuple_rules():
    rng = np.random.default_rng(0)
    states = rules.all_macrostates()[rng.integers(0, 192, 500)]
    actions = rng.integers(0, 6, 500)
    batch = rules.apply_actions(states, actions)
    for s, a, n in zip(states, actions, batch, strict=True):
        assert rules.transition(tuple(s), int(a)) == tuple(n)


def test_optimal_plan_length_by_breadth_first_search():
    assert rules.optimal_plan_length((LEFT, DOWN, RIGHT, 1), "original") == 0
    assert rules.optimal_plan_length((UP, UP, DOWN, 0), "original") is None
    assert rules.optimal_plan_length((RIGHT, UP, LEFT, 0), "original") == 1  # cube 0 clockwise
    # Three arrows leave one direction free, and a cube can only turn into the free direction
    # when it is a quarter turn away. From (UP, LEFT, RIGHT) with DOWN free, cube 0 reaches
    # DOWN in five moves, e.g. cube 1 -> DOWN, cube 0 -> LEFT, cube 2 -> UP, cube 1 -> RIGHT,
    # cube 0 -> DOWN; the paper's optimal plans were 1 to 5 actions long.
    assert rules.optimal_plan_length((UP, LEFT, RIGHT, 0), "original") == 5
    lengths = [
        rules.optimal_plan_length(tuple(s), "original") for s in rules.start_states("original")
    ]
    assert min(lengths) == 1 and max(lengths) == 5
    for task in rules.TASKS:
        for s in rules.start_states(task):
            n = rules.optimal_plan_length(tuple(s), task)
            assert n is not None and n >= 1, "every start state can be solved"
            # Bellman check: some action leads to a legal state one step closer.
            after = [
                rules.optimal_plan_length(rules.transition(tuple(s), a), task) for a in range(6)
            ]
            assert min(x for x in after if x is not None) == n - 1


def test_bad_action_and_task_messages():
    with pytest.raises(ValueError, match="invalid action 6"):
        rules.check_action(6)
    with pytest.raises(ValueError, match="invalid action -1"):
        rules.check_action(-1)
    with pytest.raises(ValueError, match="expected an integer"):
        rules.check_action(1.5)
    with pytest.raises(ValueError, match="expected an integer"):
        rules.check_action(True)
    with pytest.raises(ValueError, match="unknown task 'easy'"):
        rules.check_task("easy")


@given(
    start=st.integers(0, 191),
    actions=st.lists(st.integers(0, 5), min_size=1, max_size=30),
    task=st.sampled_from(rules.TASKS),
)
def test_any_action_sequence_keeps_the_invariants(start, actions, task):
    state = tuple(int(x) for x in rules.all_macrostates()[start])
    for a in actions:
        nxt = rules.transition(state, a)
        assert nxt[3] == state[3]  # the hand never moves
        changed = [i for i in range(3) if nxt[i] != state[i]]
        assert changed == [a // 2]  # exactly the chosen cube turns, by a quarter
        assert (nxt[a // 2] - state[a // 2]) % 4 == (1 if a % 2 == 0 else 3)
        reward = float(rules.rewards(np.array(nxt), task))
        if goal(nxt, task):
            assert reward == 50.0 and not illegal(nxt)
        elif illegal(nxt):
            assert reward == -5.0
        else:
            assert reward == -1.0
        state = nxt
