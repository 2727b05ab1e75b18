"""Never hurts (issue 57): M's trust judged by the step test, and the fallback that makes the
imaginary updates an untrusted agent skips on real batches, its real targets unexpanded."""

import pytest
import torch

import imagine.learning.population
from imagine.config import agent_preset
from imagine.errors import ConfigError
from imagine.learning.gate import one_step_close
from imagine.learning.memory import ReplayMemory
from test_gate import population


class Moving:
    """K = 2 members over 2-D states: member 0 predicts a step of +1 along x for every state,
    member 1 the same step 30% too long."""

    def member_modes(self, z, action):
        step = torch.tensor([1.0, 0.0])
        return torch.stack([z + step, z + 1.3 * step], dim=1)


def test_m_is_trusted_where_its_modes_land_within_a_share_of_the_real_step():
    pair, one = ((2,), torch.float32), ((), torch.int64)
    memory = ReplayMemory(4, {"mu": pair, "action": one, "next_mu": pair})
    for x, moved in enumerate([1.0, 1.05, 1.2, 2.5]):  # the real steps along x
        memory.add(0, mu=torch.tensor([[float(x), 0.0]]), action=torch.tensor([x % 2]),
                   next_mu=torch.tensor([[x + moved, 0.0]]))  # fmt: skip
    recent, held = memory.newest_each(4)
    # member 0 misses by 0, 0.05, 0.2, 1.5, member 1 by 0.3, 0.25, 0.1, 1.2; a tenth of the
    # steps is 0.1, 0.105, 0.12, 0.25: member 0 is within it twice, member 1 once
    assert float(one_step_close(Moving(), recent, held, 0.1)) == pytest.approx(3 / 8)
    # within half the step (0.5, 0.525, 0.6, 1.25): member 0 three times, member 1 four
    assert float(one_step_close(Moving(), recent, held, 0.5)) == pytest.approx(7 / 8)
    # scale-free: the same transitions 100 times larger are judged the same
    scaled = {k: (v * 100 if v.is_floating_point() else v) for k, v in recent.items()}

    class Scaled(Moving):
        def member_modes(self, z, action):
            return super().member_modes(z / 100, action) * 100

    assert float(one_step_close(Scaled(), scaled, held, 0.1)) == pytest.approx(3 / 8)
    empty = ReplayMemory(4, {"mu": pair, "action": one, "next_mu": pair})
    recent, held = empty.newest_each(4)
    assert float(one_step_close(Moving(), recent, held, 0.1)) == 0.0  # nothing held: untrusted


def counted(p):
    """Count, per step, the C updates of agent 0 by kind (the loss records it makes)."""
    made, record = [], p._record

    def counting(key, loss, rows):
        if key.startswith("losses/controller") and 0 in rows.tolist():
            made[-1][key] = made[-1].get(key, 0) + 1
        record(key, loss, rows)

    p._record = counting
    return made


@pytest.fixture
def expansions(monkeypatch):
    """One entry per call of value expansion through M (``expanded_target``)."""
    calls = []
    original = imagine.learning.population.expanded_target

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(imagine.learning.population, "expanded_target", counting)
    return calls


def test_an_untrusted_agent_with_the_fallback_makes_the_controls_updates(expansions):
    p = population(0, imagination_adaptive=True, imagination_fallback=True,
                   imagination_trust_test="step", imagination_trust_floor=1.0,
                   n_imaginary_updates=3, value_expansion=2, target_update_period=10)  # fmt: skip
    made, ended = counted(p), []
    for _ in range(20):
        made.append({})
        ended += [stats for _, stats in p.step()]
    assert ended and all(stats["charts/model_trusted"] == 0.0 for stats in ended)
    assert not p.trust.trusted[0]  # an M learning from 20 steps is not right on all of them
    assert p.imaginary.added[0] == 0  # an untrusted M imagines nothing: C learns from replay
    assert made == [{"losses/controller_real": 1, "losses/controller_real_extra": 3}] * 20
    assert not expansions  # and its real targets are not expanded through an untrusted M


def test_a_trusted_agent_with_the_fallback_tops_up_its_gated_updates_with_real_ones():
    p = population(0, imagination_gate="mask", imagination_gate_quantile=0.5,
                   imagination_adaptive=True, imagination_fallback=True,
                   imagination_trust_test="step", imagination_trust_floor=0.0,
                   n_imaginary_updates=4)  # fmt: skip
    made, ended = counted(p), []
    for _ in range(30):
        made.append({})
        ended += [stats for _, stats in p.step()]
    assert ended and all(stats["charts/model_trusted"] == 1.0 for stats in ended)
    imagined = [m.get("losses/controller_imaginary", 0) for m in made]
    extra = [m.get("losses/controller_real_extra", 0) for m in made]
    assert all(i + e == 4 for i, e in zip(imagined, extra, strict=True))  # N_I every step
    assert sum(imagined) > 0 and sum(extra) > 0  # trusted: imagined, but fewer than N_I


def test_the_fallback_and_the_step_test_refuse_bad_settings_in_one_line():
    cases = [
        ({"imagination_fallback": True}, "agent.imagination_fallback makes the imaginary "
         "updates an adaptive agent skips on real batches: set agent.imagination_adaptive=true"),
        ({"imagination_trust_test": "vibes"},
         "agent.imagination_trust_test must be one of action, step, got 'vibes'"),
        ({"imagination_trust_tolerance": 0.0},
         "agent.imagination_trust_tolerance must be > 0, got 0.0"),
    ]  # fmt: skip
    for overrides, message in cases:
        with pytest.raises(ConfigError) as error:
            agent_preset("fast", **overrides)
        assert str(error.value) == message


def test_an_agent_switched_to_the_papers_rollouts_counts_as_trusted_by_the_fallback(expansions):
    # every action's backups in episode 0, the paper's policy rollouts from episode 1 on,
    # where M is not judged (a floor of 1.0 would never pass it)
    p = population(0, imagination_adaptive=True, imagination_fallback=True,
                   imagination_trust_test="step", imagination_trust_floor=1.0,
                   imagination_actions="all", imagination_actions_until=1,
                   n_imaginary_updates=3, value_expansion=2)  # fmt: skip
    while p.episode[0] < 1:
        p.step()
    assert p.imaginary.added[0] == 0 and not p.trust.trusted[0]  # untrusted in episode 0
    expansions.clear()
    made = counted(p)
    for _ in range(10):
        made.append({})
        p.step()
    assert p.imaginary.added[0] > 0  # it imagines, ungated
    assert expansions  # and expands its real targets through M
    assert all(m.get("losses/controller_imaginary") == 3 for m in made)  # N_I on M_I
    assert not any("losses/controller_real_extra" in m for m in made)  # none on replay


def test_the_fast_augmented_agent_on_state_vectors_has_m_without_dropout_and_the_fallback():
    on_vectors = agent_preset("fast", env="CartPole-v1", encoder="vector")
    assert on_vectors.dropout == 0.0
    assert on_vectors.imagination_fallback and on_vectors.imagination_adaptive
    assert on_vectors.imagination_trust_test == "step"
    on_latents = agent_preset("fast")  # GesturePuzzle through V keeps the preset's M
    assert on_latents.dropout == 0.2 and not on_latents.imagination_fallback
    # the baseline has no M to judge, the paper's preset stays the paper's, a user's choice wins
    assert not agent_preset("fast", method="baseline", encoder="vector").imagination_fallback
    assert agent_preset("paper", env="CartPole-v1", encoder="vector").dropout == 0.5
    chosen = agent_preset("fast", env="CartPole-v1", encoder="vector", dropout=0.3,
                          imagination_fallback=False)  # fmt: skip
    assert chosen.dropout == 0.3 and not chosen.imagination_fallback
