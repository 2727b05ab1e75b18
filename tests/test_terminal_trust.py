"""d, the terminal network, where failures are rare (issue 57): M's trust judged on d as well
as on its next state, and d's cross-entropy weighted so that both classes weigh the same."""

import pytest
import torch

import imagine.learning.population
from imagine.config import agent_preset
from imagine.errors import ConfigError
from imagine.learning.gate import terminal_right
from imagine.learning.memory import ReplayMemory
from imagine.models.world_model import PopulationWorldModel, WorldModel
from test_gate import population

ONE, FLAG = ((1,), torch.float32), ((), torch.float32)


def ring(capacity: int, ends: list[list[float]]) -> ReplayMemory:
    """Agents' memories of 1-D transitions in the order given: transition j of an agent has
    next_mu j and done ends[agent][j]."""
    memory = ReplayMemory(capacity, {"next_mu": ONE, "done": FLAG}, len(ends))
    for agent, done in enumerate(ends):
        for j, d in enumerate(done):
            memory.add(agent, next_mu=torch.tensor([[float(j)]]), done=torch.tensor([d]))
    return memory


def test_the_newest_terminal_transitions_are_found_newest_first_across_the_ring():
    # capacity 4, six transitions: j = 0 and 1 are overwritten; held: j = 2, 3, 4, 5
    memory = ring(4, [[1, 1, 0, 1, 0, 1], [0, 0, 0, 0, 0, 0], [1, 0]])
    ends, held = memory.newest_where("done", 3)
    assert held.tolist() == [[True, True, False], [False, False, False], [True, False, False]]
    assert ends["next_mu"][0, :2, 0].tolist() == [5.0, 3.0]  # the overwritten j = 0, 1 gone
    assert ends["next_mu"][2, 0, 0].item() == 0.0
    assert ends["done"][held].eq(1).all()


class Calls:
    """A d that calls the states with next_mu 3 or 4 terminal."""

    def is_terminal(self, z):
        return (z[..., 0] == 3) | (z[..., 0] == 4)


def test_d_is_judged_by_the_lower_of_its_recall_and_its_specificity():
    memory = ring(8, [
        [0, 0, 1, 0, 1, 0],  # terminals 2 (missed) and 4: recall 1/2; 3 called of 0, 1, 3, 5
        [0, 0, 0, 1, 0, 0],  # terminal 3 called; 4 called too: 4 of the 5 others right
        [0, 0, 0],  # no terminal yet: judged on the others alone, all right
    ])  # fmt: skip
    assert terminal_right(Calls(), memory, 10).tolist() == pytest.approx([0.5, 4 / 5, 1.0])
    # on its newest terminal alone (4, called) agent 0's d is held back by its specificity
    assert terminal_right(Calls(), memory, 1)[0].item() == pytest.approx(3 / 4)


def test_an_m_with_its_next_state_right_is_not_trusted_while_d_is_wrong(monkeypatch):
    # the step test passes every M here, so whether M is trusted is d's judgment alone
    monkeypatch.setattr(imagine.learning.population, "one_step_close",
                        lambda model, recent, held, tolerance: torch.ones(len(held)))  # fmt: skip
    judged = {"imagination_adaptive": True, "imagination_trust_test": "step",
              "imagination_trust_every": 1}  # fmt: skip
    p = population(0, **judged, imagination_trust_terminals=5)
    unjudged = population(0, **judged)
    while p.real.data["done"][0, : p.real.size[0]].sum() == 0:
        p.step()
        unjudged.step()
    never = lambda z: torch.zeros(z.shape[:-1], dtype=torch.bool)  # noqa: E731
    p.model.is_terminal = unjudged.model.is_terminal = never
    p.step()
    unjudged.step()
    assert not p.trust.trusted[0]  # d calls none of the failures terminal: recall 0
    assert unjudged.trust.trusted[0]  # the same M, d not judged
    p.model.is_terminal = lambda z: torch.ones(z.shape[:-1], dtype=torch.bool)
    p.step()
    assert not p.trust.trusted[0]  # d calls everything terminal: specificity 0


def test_bad_terminal_settings_are_refused_in_one_line():
    cases = [
        ({"terminal_weight": "heavy"},
         "agent.terminal_weight must be one of none, balanced, got 'heavy'"),
        ({"imagination_trust_terminals": -1},
         "agent.imagination_trust_terminals must be >= 0, got -1"),
    ]  # fmt: skip
    for overrides, message in cases:
        with pytest.raises(ConfigError) as error:
            agent_preset("fast", **overrides)
        assert str(error.value) == message


def test_balanced_weights_each_terminal_as_the_others_per_terminal_in_m_r():
    p = population(0, terminal_weight="balanced")
    assert p._terminal_weight().tolist() == [1.0]  # nothing held: as sampled
    while p.real.data["done"][0, : p.real.size[0]].sum() < 2:
        p.step()
    ends = float(p.real.data["done"][0].sum())
    assert p._terminal_weight().tolist() == pytest.approx([(p.real.size[0] - ends) / ends])
    assert population(0)._terminal_weight() is None  # the paper's d: as sampled


def test_a_terminal_weight_scales_the_terminal_transitions_loss_in_d():
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(2, 2, dropout=0.0)])
    batch = {"mu": torch.randn(1, 8, 2), "sigma": torch.zeros(1, 8, 2),
             "action": torch.zeros(1, 8, dtype=torch.int64), "next_mu": torch.randn(1, 8, 2),
             "next_sigma": torch.zeros(1, 8, 2), "reward": torch.zeros(1, 8),
             "done": torch.tensor([[1.0] + [0.0] * 7])}  # fmt: skip
    state = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():  # -log sigmoid(logit) of the terminal transition, before any step
        terminal = torch.nn.functional.softplus(-model.terminal(batch["next_mu"])[0, 0, 0])
    gens = [torch.Generator().manual_seed(0)]
    plain = model.update(batch, gens, resample=False, mdn=False)["terminal"]
    model.load_state_dict(state)
    weighted = model.update(batch, gens, resample=False, mdn=False,
                            terminal_weight=torch.tensor([7.0]))["terminal"]  # fmt: skip
    # weight 7: the terminal one counts 6 more times in the batch's mean of 8
    assert float(weighted - plain) == pytest.approx(float(6 * terminal / 8), rel=1e-5)
