"""Plans (paper Fig. 5) and model generalization (paper Fig. 7): the plan judge knows an optimal
plan, a longer successful one and a failed one; the commands write their files."""

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imagine.envs.gesture_puzzle.rules import (
    apply_actions,
    is_goal,
    is_illegal,
    optimal_plan_length,
    start_states,
)
from imagine.study.planning import judge_plan

IMAGINE = str(Path(sys.executable).parent / "imagine")


def outcome(start, actions, task):
    """Brute-force truth: 'goal' at the last action, 'early' before it, or 'fail'."""
    state = np.asarray(start)
    for i, a in enumerate(actions):
        state = apply_actions(state, np.asarray(a))
        if is_illegal(state[None])[0]:
            return "fail"
        if is_goal(state[None], task)[0]:
            return "goal" if i == len(actions) - 1 else "early"
    return "fail"


@pytest.mark.parametrize("task", ["original", "hard"])
def test_the_plan_judge_knows_optimal_longer_and_failed_plans(task):
    start = next(s for s in start_states(task) if optimal_plan_length(tuple(s), task) == 2)
    plans = {n: [p for p in itertools.product(range(6), repeat=n)
                 if outcome(start, p, task) == "goal"] for n in (1, 2, 4)}  # fmt: skip
    assert not plans[1] and plans[2] and plans[4]
    optimal = judge_plan(start, list(plans[2][0]), task)
    assert optimal.success and optimal.optimal and optimal.optimal_length == 2
    longer = judge_plan(start, list(plans[4][0]), task)
    assert longer.success and not longer.optimal and longer.steps == 4
    failed_plan = next(p for p in itertools.product(range(6), repeat=2)
                       if outcome(start, p, task) == "fail")  # fmt: skip
    failed = judge_plan(start, list(failed_plan), task)
    assert not failed.success and not failed.optimal
    assert not judge_plan(start, [], task).success  # an empty plan solves nothing


def test_plan_and_generalize_commands(tmp_path):
    run = tmp_path / "run"
    done = subprocess.run([IMAGINE, "train", str(run), "--preset", "smoke", "--oracle",
                           "--episodes", "30", "--set", "imagination_start=10",
                           "--set", "model_ensemble=2"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = subprocess.run([IMAGINE, "plan", str(run), "--trials", "5"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "plans succeeded" in done.stdout
    plans = json.loads((run / "plans.json").read_text())
    assert plans["trials"] == 5 and len(plans["plans"]) == 5
    assert all(p["optimal_length"] is not None for p in plans["plans"])  # from start states
    done = subprocess.run([IMAGINE, "generalize", str(run), "--trials", "7"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads((run / "generalization.json").read_text())
    assert result["trials"] == 7 and result["all_terminal_transitions"] == 138 * 6
    assert 0.0 <= result["all_terminal_accuracy"] <= 1.0
    # M is an ensemble: the members' mean mode above, its first member alone beside it
    assert 0.0 <= result["all_terminal_accuracy_first_member"] <= 1.0


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a GPU")
def test_plans_and_predictions_take_vs_means_from_another_device():
    """A study's snapshot agent on a GPU keeps V there and M and C on the CPU: plans and M's
    predictions from terminal states move V's means to M's device (the same numbers)."""
    from types import SimpleNamespace

    import torch

    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.models.controller import Controller
    from imagine.models.world_model import WorldModel
    from imagine.study.generalization import predict_next
    from imagine.study.planning import imagine_plan

    class OnGpu(OracleEncoder):
        def encode(self, images, states):
            mu, sigma = super().encode(images, states)
            return mu.cuda(), sigma.cuda()

    torch.manual_seed(0)
    agent = SimpleNamespace(model=WorldModel(8, dropout=0.0), controller=Controller(8))
    states, actions = start_states("hard")[:4], np.arange(4)
    images = np.zeros((4, 64, 64, 3), dtype=np.uint8)
    mu, _ = OracleEncoder().encode(images, states)
    plan, latents = imagine_plan(agent, mu[0])
    on_gpu, gpu_latents = imagine_plan(agent, mu[0].cuda())
    assert on_gpu == plan and torch.allclose(gpu_latents.cpu(), latents)
    gpu = SimpleNamespace(**vars(agent), encoder=OnGpu())
    cpu = SimpleNamespace(**vars(agent), encoder=OracleEncoder())
    assert torch.allclose(predict_next(gpu, images, states, actions)[0],
                          predict_next(cpu, images, states, actions)[0])  # fmt: skip


@pytest.mark.parametrize("training", [True, False])
def test_plans_and_predictions_leave_m_and_c_in_the_mode_they_found(training):
    """Plans and M's predictions run without dropout and hand M and C back as they were: a
    loaded agent stays in eval mode for what a caller does next, a training one in train."""
    from types import SimpleNamespace

    import torch

    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.models.controller import Controller
    from imagine.models.world_model import WorldModel
    from imagine.study.generalization import next_from
    from imagine.study.planning import imagine_plan

    torch.manual_seed(0)
    agent = SimpleNamespace(model=WorldModel(8, dropout=0.5, ensemble=2),
                            controller=Controller(8))  # fmt: skip
    agent.model.train(training)
    agent.controller.train(training)
    mu, _ = OracleEncoder().encode(np.zeros((4, 64, 64, 3), np.uint8), start_states("hard")[:4])
    first = next_from(agent, mu, np.arange(4))
    assert agent.model.training is training
    torch.testing.assert_close(next_from(agent, mu, np.arange(4)), first)  # no dropout draws
    imagine_plan(agent, mu[0])
    assert agent.model.training is training and agent.controller.training is training
    assert all(m.training is training for m in agent.model.modules())
