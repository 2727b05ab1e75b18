"""Issue 15, model trust: gated imagination (stop, mask, the random control), the threshold
from recent first-step disagreements, its ring in the checkpoint, and the adaptive N_I."""

import dataclasses
import math

import pytest
import torch

from imagine.checkpoint import load_tensors
from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.envs.gesture_puzzle.evaluation import imagined_accuracy
from imagine.errors import ConfigError
from imagine.learning.agent import load_agent
from imagine.learning.gate import (
    FAR,
    ModelTrust,
    gate_transitions,
    imaginary_updates,
    one_step_right,
    support_distance,
)
from imagine.learning.imagination import imagine_rollouts
from imagine.learning.memory import ReplayMemory
from imagine.learning.population import EpisodeTotals, Population
from imagine.learning.training import train_population
from imagine.metrics import read_metrics
from imagine.models.controller import Controller, PopulationController
from imagine.models.world_model import Prediction
from test_imagination_fix import RuleModel

SCHEDULE = torch.tensor([[0.1, 0.2, 0.3],  # step 0 of rollouts 0, 1, 2
                         [0.5, 2.0, 0.1],  # step 1: rollout 1 over 1.0
                         [0.1, 0.1, 3.0],  # step 2: rollout 2 over
                         [2.5, 0.1, 0.1]])  # step 3: rollout 0 over  # fmt: skip


class ScheduledModel(RuleModel):
    """M that knows the rules, never ends a rollout, and whose members disagree by a fixed
    schedule: at its t-th prediction, rollout b's disagreement is ``schedule[t, b]``."""

    def __init__(self, schedule: torch.Tensor) -> None:
        super().__init__(OracleEncoder(), "original")
        self.schedule, self.t = schedule, 0

    def predict(self, z, action, generators, draw):
        spread = self.schedule[self.t].expand(z.shape[:-1])
        self.t += 1
        return Prediction(self._next(z, action), spread)

    def is_terminal(self, z):
        return torch.zeros(z.shape[:-1], dtype=torch.bool)


def scheduled_rollouts() -> dict[str, torch.Tensor]:
    """3 rollouts of 4 steps with :data:`SCHEDULE`'s disagreements (unit scale)."""
    encoder = OracleEncoder()
    mu, _ = encoder.encode(None, torch.tensor([[0, 1, 2, 0]]).numpy())
    torch.manual_seed(0)
    controller = PopulationController([Controller(8)])
    return imagine_rollouts(ScheduledModel(SCHEDULE), controller, mu, torch.zeros_like(mu), 3, 4,
                            [0.0], [torch.Generator().manual_seed(0)], draw="mode",
                            scale=torch.ones(1))[0]  # fmt: skip


def gate(rule: str, rollout, threshold=1.0, seed=0) -> list[bool]:
    generator = torch.Generator().manual_seed(seed)
    return gate_transitions(rule, rollout["disagreement"], rollout["rollout"], rollout["step"],
                            threshold, generator).tolist()  # fmt: skip


T, F = True, False


def test_rollouts_say_which_rollout_and_step_each_transition_is():
    rollout = scheduled_rollouts()
    assert rollout["step"].tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3]
    assert rollout["rollout"].tolist() == [0, 1, 2] * 4
    assert torch.equal(rollout["disagreement"], SCHEDULE.flatten())


def test_stop_ends_a_rollout_at_its_first_step_over_the_threshold():
    # rollout 0 over at step 3, rollout 1 at step 1, rollout 2 at step 2
    kept = [[T, T, T], [T, F, T], [T, F, F], [F, F, F]]  # by step, then rollout
    assert gate("stop", scheduled_rollouts()) == [x for step in kept for x in step]
    assert gate("stop", scheduled_rollouts(), threshold=10.0) == [T] * 12


def test_mask_drops_exactly_the_transitions_over_the_threshold():
    kept = [[T, T, T], [T, F, T], [T, T, F], [F, T, T]]  # by step, then rollout
    assert gate("mask", scheduled_rollouts()) == [x for step in kept for x in step]
    assert gate("none", scheduled_rollouts()) == [T] * 12


def test_random_drops_as_many_as_mask_but_at_random():
    rollout = scheduled_rollouts()
    draws = [gate("random", rollout, seed=s) for s in range(20)]
    assert all(d.count(False) == 3 for d in draws)  # mask drops 3
    assert draws[0] == gate("random", rollout, seed=0)  # from the generator alone
    assert len({tuple(d) for d in draws}) > 5
    assert any(d != gate("mask", rollout) for d in draws)


def trust_of(**overrides) -> ModelTrust:
    config = agent_preset("smoke", model_ensemble=2, imagination_gate="mask", **overrides)
    return ModelTrust(config, 1, torch.device("cpu"))


def test_the_threshold_is_scale_times_the_quantile_of_recent_first_steps():
    trust = trust_of(imagination_gate_window=5, imagination_gate_quantile=0.5,
                     imagination_gate_scale=2.0)  # fmt: skip
    steps = [torch.tensor([0.1, 0.9, 0.4]), torch.tensor([5.0, 0.2, 0.3]),
             torch.tensor([0.6, 0.7, 0.8])]  # fmt: skip
    shares = []
    for first in steps:  # one rollout step deep: every transition a first step
        keep = trust.gate(0, first, torch.arange(3), torch.zeros(3, dtype=torch.int64), None)
        threshold = float(trust.threshold(0))
        assert torch.equal(keep, first <= threshold)
        shares.append(float(keep.float().mean()))
    # the ring holds the last 5 first steps: 0.3, 0.2 and 0.6, 0.7, 0.8 (0.1, 0.9, 0.4 and
    # 5.0 forgotten); their median is 0.6
    recent = torch.tensor([0.2, 0.3, 0.6, 0.7, 0.8])
    assert trust.threshold(0) == pytest.approx(2.0 * float(torch.quantile(recent, 0.5)))
    assert trust.threshold(0) == pytest.approx(1.2)
    assert trust.acceptance[0] == pytest.approx(sum(shares) / 3)  # the plain mean so far


def test_bad_gate_settings_are_refused_in_one_line():
    cases = [
        ("imagination_gate", "maybe", "agent.imagination_gate must be one of none, stop, mask, "
         "random, got 'maybe'"),
        ("imagination_gate", "stop", "agent.imagination_gate stop needs the members' "
         "disagreement: set agent.model_ensemble >= 2 (got 1) or "
         "agent.imagination_uncertainty=support"),
        ("imagination_uncertainty", "vibes", "agent.imagination_uncertainty must be one of "
         "disagreement, support, got 'vibes'"),
        ("imagination_gate_quantile", 0.0,
         "agent.imagination_gate_quantile must be in (0, 1], got 0.0"),
        ("imagination_gate_quantile", 1.5,
         "agent.imagination_gate_quantile must be in (0, 1], got 1.5"),
        ("imagination_gate_scale", 0.0, "agent.imagination_gate_scale must be positive, got 0.0"),
        ("imagination_gate_window", 0, "agent.imagination_gate_window must be positive, got 0"),
        ("imagination_trust_floor", 1.5,
         "agent.imagination_trust_floor must be in [0, 1], got 1.5"),
        ("imagination_trust_every", 0, "agent.imagination_trust_every must be >= 1, got 0"),
    ]  # fmt: skip
    for key, value, message in cases:
        with pytest.raises(ConfigError) as error:
            agent_preset("paper", **{key: value})
        assert str(error.value) == message
    config = agent_preset("paper")  # the paper's plain imagination
    assert (config.imagination_gate, config.imagination_adaptive) == ("none", False)


def population(steps: int, ended: list | None = None, **overrides) -> Population:
    """A gated agent after ``steps`` real steps; the statistics of its finished episodes are
    appended to ``ended``."""
    config = agent_preset("smoke", encoder="oracle", imagination_start=0, imagination_depth=4,
                          seed=3, **{"model_ensemble": 2, **overrides})  # fmt: skip
    p = Population([config], OracleEncoder())
    for _ in range(steps):
        stats = p.step()
        if ended is not None:
            ended += [s for _, s in stats]
    return p


def test_support_is_the_distance_to_the_nearest_real_start_with_the_same_action():
    memory_mu = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 3.0]])
    memory_action = torch.tensor([0, 1, 0])
    z = torch.tensor([[0.9, 0.0], [0.9, 0.0], [0.0, 2.0], [0.5, 0.5]])
    u = support_distance(z, torch.tensor([0, 1, 0, 2]), memory_mu, memory_action)
    assert u[:3].tolist() == pytest.approx([0.9, 0.1, 1.0])
    assert u[3] == FAR  # the agent never took action 2: as far as can be
    assert support_distance(z, torch.zeros(4, dtype=torch.int64), memory_mu[:0],
                            memory_action[:0]).eq(FAR).all()  # fmt: skip


def test_a_support_gate_needs_no_ensemble_and_keeps_what_m_has_data_for():
    settings = {"model_ensemble": 1, "imagination_uncertainty": "support"}
    plain = population(20, model_ensemble=1)
    wide = population(20, imagination_gate="mask", imagination_gate_quantile=1.0,
                      imagination_gate_scale=1e9, **settings)  # fmt: skip
    for name, value in plain.imaginary.data.items():  # nothing dropped: no gate at all
        assert torch.equal(wide.imaginary.data[name], value), name
    ended = []
    gated = population(30, ended, imagination_gate="mask", imagination_gate_quantile=0.5,
                       **settings)  # fmt: skip
    assert wide.imaginary.added[0] > 0 and plain.imaginary.added[0] > 0
    imagined = sum(s["charts/imagined_transitions"] for s in ended)
    accepted = sum(s["charts/imagined_accepted"] * s["charts/imagined_transitions"]
                   for s in ended)  # fmt: skip
    assert 0 < accepted < imagined  # the median threshold drops some
    kept = gated.imaginary.size[0]
    u = gated._support(0, gated.imaginary.data["z"][0, :kept],
                       gated.imaginary.data["action"][0, :kept])  # fmt: skip
    assert (u < FAR).all()
    assert ended[-1]["charts/imagined_disagreement"] > 0  # the mean u, logged


def test_a_gate_that_drops_nothing_is_bitwise_no_gate():
    """The gate only filters what was imagined: with a threshold nothing reaches, M_I, C and M
    are those of an agent without one (which are today's: the rollouts and their draws are
    unchanged)."""
    plain = population(20)
    for rule in ("mask", "stop", "random"):
        gated = population(20, imagination_gate=rule, imagination_gate_quantile=1.0,
                           imagination_gate_scale=1e9)  # fmt: skip
        assert gated.imaginary.added == plain.imaginary.added
        for name, value in plain.imaginary.data.items():
            assert torch.equal(gated.imaginary.data[name], value), (rule, name)
        for a, b in ((plain.controller, gated.controller), (plain.model, gated.model)):
            for (name, p), q in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
                assert torch.equal(p, q), (rule, name)
    assert "charts/imagined_accepted" not in EpisodeTotals(imagined=5).stats()


def test_a_gated_agent_stores_what_it_accepts_and_logs_the_share():
    ended = []
    p = population(30, ended, imagination_gate="mask", imagination_gate_quantile=0.5)
    episodes = [*ended, p._episode[0].stats()]
    imagined = [s["charts/imagined_transitions"] for s in episodes]
    accepted = [s["charts/imagined_accepted"] * n for s, n in zip(episodes, imagined, strict=True)]
    assert sum(accepted) == pytest.approx(p.imaginary.added[0])  # M_I holds what was accepted
    assert 0 < sum(accepted) < sum(imagined)  # a median threshold drops some
    assert p.trust.first_steps.added[0] == 30 * 3  # every rollout's first step, kept or not


def test_adaptive_n_i_is_zero_while_m_is_not_trusted():
    p = population(30, imagination_adaptive=True, imagination_trust_floor=1.0,
                   n_imaginary_updates=4)  # fmt: skip
    assert p.imaginary.added[0] > 0  # it imagines, but C never learns from it
    assert "losses/controller_imaginary" not in p._loss_count


def test_trust_is_judged_every_few_real_steps_and_holds_in_between(monkeypatch):
    import imagine.learning.population

    judged = []

    def counting(model, recent, valid, n_actions):
        judged.append(int(valid.sum()))  # real transitions held when judged
        return torch.ones(valid.shape[0])

    monkeypatch.setattr(imagine.learning.population, "one_step_right", counting)
    p = population(12, imagination_adaptive=True, imagination_trust_every=4)
    assert len(judged) == 3  # at the agent's real steps 0, 4 and 8 of 12
    assert judged == sorted(judged) and judged[-1] > judged[0]  # on newer transitions each time
    assert p.trust.trusted[0] and 0 <= p.t[0] - 1 - p.trust.judged_at[0] < 4
    judged.clear()
    population(12, imagination_adaptive=True, imagination_trust_every=1)
    assert len(judged) == 12


def test_trust_judgment_round_trips_and_an_older_checkpoint_judges_at_once():
    trust = ModelTrust(agent_preset("smoke", imagination_adaptive=True), 2, torch.device("cpu"))
    trust.judge(1, t=7, right=0.9)
    assert trust.trusted[1] and not trust.due(1, 16) and trust.due(1, 17) and trust.due(0, 0)
    tensors = trust.state_dict("gate", 1)
    again = ModelTrust(trust.config, 2, torch.device("cpu"))
    again.load_state_dict(tensors, "gate", 0)
    assert again.trusted[0] and again.judged_at[0] == 7
    del tensors["gate.trust"]  # written before trust was judged every few steps
    again.load_state_dict(tensors, "gate", 0)
    assert not again.trusted[0] and again.due(0, 8)


def test_adaptive_n_i_is_n_i_times_the_running_acceptance_once_m_is_trusted():
    p = population(0, imagination_gate="mask", imagination_gate_quantile=0.5,
                   imagination_adaptive=True, imagination_trust_floor=0.0,
                   n_imaginary_updates=4)  # fmt: skip
    expected, made, record = [], [], p._record

    def counting(key, loss, rows):  # the imaginary C updates agent 0 makes
        if key == "losses/controller_imaginary" and 0 in rows.tolist():
            made[-1] += 1
        record(key, loss, rows)

    p._record = counting
    for _ in range(30):
        made.append(0)
        p.step()
        expected.append(math.floor(4 * p.trust.acceptance[0] + 0.5))
    assert made == expected
    assert len(set(made)) > 1, made  # the acceptance, and with it N_I', moves
    assert imaginary_updates(4, 0.625, True) == 3 and imaginary_updates(4, 0.625, False) == 0
    assert imaginary_updates(1, 0.5, True) == 1  # halves round up


class ShiftByAction:
    """K = 2 members over 2-D latents: member 0 moves the state by (a, 0) for action a (it
    tells every action apart); member 1 predicts the same next state for every action."""

    def member_modes(self, z, action):
        moved = z + torch.stack([action.float(), torch.zeros_like(action.float())], -1)
        return torch.stack([moved, z + 0.5], dim=1)


def test_m_is_trusted_where_its_modes_identify_the_action_taken():
    pair, one = ((2,), torch.float32), ((), torch.int64)
    memory = ReplayMemory(6, {"mu": pair, "action": one, "next_mu": pair})
    for x in range(8):  # wraps: the newest four are x = 4..7
        action = x % 3
        noise = 0.4 if x == 7 else 0.0  # the newest lands nearer the mode of another action
        memory.add(0, mu=torch.full((1, 2), float(x)),
                   action=torch.tensor([action]),
                   next_mu=torch.tensor([[x + action + 0.6 * (noise > 0), float(x)]]))  # fmt: skip
    recent, held = memory.newest_each(4)
    assert recent["mu"][0, :, 0].tolist() == [4.0, 5.0, 6.0, 7.0] and bool(held.all())
    # member 0 identifies 3 of the 4 actions; member 1 ignores the action, so its modes tie
    # three ways, each counting 1/3 (chance): (3 + 4/3) / 8
    right = one_step_right(ShiftByAction(), recent, held, n_actions=3)
    assert float(right) == pytest.approx((3 + 4 / 3) / 8)
    # no unit enters: the same transitions 100 times larger are judged the same
    scaled = {k: (v * 100 if v.is_floating_point() else v) for k, v in recent.items()}

    class Scaled(ShiftByAction):
        def member_modes(self, z, action):
            return super().member_modes(z / 100, action) * 100

    assert float(one_step_right(Scaled(), scaled, held, n_actions=3)) == pytest.approx(float(right))
    fresh = ReplayMemory(6, {"mu": ((2,), torch.float32)})
    fresh.add(0, mu=torch.ones(1, 2))
    assert fresh.newest_each(3)[1].tolist() == [[False, False, True]]


@pytest.fixture(scope="module")
def gated_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gate") / "run"
    config = agent_preset("smoke", encoder="oracle", method="augmented", episodes=30,
                          imagination_start=10, log_every=10, checkpoint_every=10,
                          accuracy_every=10, model_ensemble=2, imagination_gate="mask",
                          imagination_gate_quantile=0.5, imagination_gate_window=30,
                          imagination_adaptive=True, imagination_trust_floor=0.0,
                          n_imaginary_updates=3)  # fmt: skip
    train_population([config], [folder], threads=1)
    return config, folder


def numbers(folder):
    return [{k: v for k, v in row.items() if not k.startswith("time")}
            for row in read_metrics(folder / "metrics.csv")]  # fmt: skip


def test_a_resumed_agent_gates_as_one_that_never_stopped(gated_run, tmp_path):
    config, straight = gated_run
    resumed = tmp_path / "resumed"
    train_population([dataclasses.replace(config, episodes=20)], [resumed], threads=1)
    halfway = load_tensors(resumed / "agent.safetensors", "agent checkpoint")
    assert len(halfway["gate.first_steps.disagreement"]) == 30  # the ring, full and wrapped
    assert int(halfway["gate.first_steps._counters"][2]) > 30
    train_population([config], [resumed], threads=1)
    assert numbers(resumed) == numbers(straight)
    a, b = (load_tensors(f / "agent.safetensors", "agent checkpoint") for f in (straight, resumed))
    gate_keys = [k for k in a if k.startswith("gate.")]
    assert len(gate_keys) == 4 and all(torch.equal(a[k], b[k]) for k in gate_keys)
    for (name, p), q in zip(load_agent(straight).controller.state_dict().items(),
                            load_agent(resumed).controller.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(p, q), name
    accepted = [row["charts/imagined_accepted"] for row in numbers(straight)[1:]]
    assert all(0 < x < 1 for x in accepted), accepted


def test_evaluate_reports_what_the_gate_accepts_and_how_right_it_is(gated_run, capsys):
    from imagine.cli import evaluate_agent

    _, folder = gated_run
    out = imagined_accuracy(load_agent(folder), starts=20)
    n, accepted = out["transitions"], out["accepted"]
    assert 0 < accepted < 1
    assert 0 <= out["support_auroc"] <= 1 or math.isnan(out["support_auroc"])
    right = n * accepted * out["state_accepted"] + n * (1 - accepted) * out["state_rejected"]
    assert right == pytest.approx(n * out["state"])
    assert out["gate_threshold"] > 0 and not math.isnan(out["state_rejected"])
    evaluate_agent(folder, episodes=10, seed=0)
    assert "gate mask on disagreement at q 0.5, scale 1.0: threshold" in capsys.readouterr().out


def test_a_gated_agent_in_a_population_gates_as_it_does_alone():
    settings = {"encoder": "oracle", "imagination_start": 0, "imagination_depth": 4,
                "model_ensemble": 2, "imagination_gate": "random",
                "imagination_gate_quantile": 0.5, "imagination_adaptive": True,
                "imagination_trust_floor": 0.0, "n_imaginary_updates": 3}  # fmt: skip
    configs = [agent_preset("smoke", seed=s, **settings) for s in (3, 4)]
    together = Population(configs, OracleEncoder())
    alone = [Population([c], OracleEncoder()) for c in configs]
    for _ in range(15):
        for p in (together, *alone):
            p.step()
    for i, p in enumerate(alone):
        # C's updates: 15 real ones, and imaginary ones as many as each acceptance allows
        assert 15 < int(together.controller.updates[i]) == int(p.controller.updates[0])
        assert together.trust.acceptance[i] == p.trust.acceptance[0]
        assert together.imaginary.added[i] == p.imaginary.added[0]
        assert torch.equal(together.trust.threshold(i), p.trust.threshold(0))
        for name, value in p.imaginary.data.items():
            assert torch.equal(together.imaginary.data[name][i], value[0]), name
        controller, _ = together.networks(i)
        for (name, w), v in zip(controller.state_dict().items(),
                                p.networks(0)[0].state_dict().values(), strict=True):  # fmt: skip
            assert torch.equal(w, v), name
    assert together.trust.acceptance[0] != together.trust.acceptance[1]
