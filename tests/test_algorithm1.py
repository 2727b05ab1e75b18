"""The reference Algorithm 1 (:mod:`imagine.learning.algorithm1`, one agent, no population axis)
against the population that trains the agents of every study: for one seed of the `fast`
preset, every update of C and M has the same loss, bitwise, in the same order, and the trained
networks end equal.

Bitwise, not a tolerance: the reference draws every random number in the population's order
and runs the same kernels on the same shapes (the stacked layers with one row; a plain
``nn.Linear`` rounds a one-unit output and a product of 1 to 3 rows otherwise, and from there
the two runs drift apart, 1e-3 in d's loss after 100 steps, different episodes by 300)."""

from __future__ import annotations

import pytest
import torch

import toy_envs  # noqa: F401  (registers the toy environments)
from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.errors import ConfigError
from imagine.learning import algorithm1
from imagine.learning.agent import Agent
from imagine.learning.population import Population
from imagine.models.encoders import VectorEncoder

Log = list[tuple[str, torch.Tensor]]


def population_run(config, encoder) -> tuple[Log, Population]:
    """Every update's loss of a population of one, in order: each of M's three networks and
    C's, through the networks' own ``update``."""
    population, log = Population([config], encoder), []
    model_update, controller_update = population.model.update, population.controller.update

    def update_model(*args, **kwargs):
        losses = model_update(*args, **kwargs)
        log.extend((f"losses/{key}", loss[0]) for key, loss in losses.items())
        return losses

    def update_controller(*args, **kwargs):
        loss = controller_update(*args, **kwargs)
        log.append(("losses/controller", loss[0]))
        return loss

    population.model.update, population.controller.update = update_model, update_controller
    while not population.finished(0):
        population.step()
    return log, population


def reference_run(config, encoder) -> tuple[Log, Agent]:
    log: Log = []

    def record(key: str, loss: torch.Tensor) -> None:  # real and imaginary batches: one C
        log.append(("losses/controller" if "controller" in key else key, loss))

    return log, algorithm1.train(config, encoder, record)


def assert_same_run(config, encoder) -> Log:
    (expected, population), (got, agent) = (
        population_run(config, encoder),
        reference_run(config, encoder),
    )
    assert [key for key, _ in got] == [key for key, _ in expected]
    for n, ((key, a), (_, b)) in enumerate(zip(got, expected, strict=True)):
        assert torch.equal(a, b), f"update {n} ({key}): reference {a.item()} != {b.item()}"
    assert (agent.episode, agent.t) == (population.episode[0], population.t[0])
    for mine, theirs in zip((agent.controller, agent.model), population.networks(0), strict=True):
        for (name, p), q in zip(mine.state_dict().items(), theirs.state_dict().values(),
                                strict=True):  # fmt: skip
            assert torch.equal(p, q), name
    return got


def count(log: Log, key: str) -> int:
    return sum(k == key for k, _ in log)


def test_the_augmented_agent_has_the_populations_losses():
    """The `fast` augmented agent: an ensemble of 5 MDNs with the mask gate, residual M,
    imagination from M_R by M's mode, MVE with H = 2, reward_updates, N_I = 3, a target
    network every 100 C updates. I_start at episode 20 (about step 30 of 150) so that most
    steps imagine, and M's batches of 32 instead of 128 to keep the test to seconds (sizes
    change no random stream's order)."""
    config = agent_preset("fast", encoder="oracle", method="augmented", steps=150,
                          imagination_start=20, model_batch=32)  # fmt: skip
    log = assert_same_run(config, OracleEncoder(config.oracle_sigma))
    assert count(log, "losses/mdn") == 150 * config.model_updates
    assert count(log, "losses/reward") == 150 * (config.model_updates + config.reward_updates)
    imaginary = count(log, "losses/controller") - 150 * config.n_real_updates
    assert imaginary > 80 * config.n_imaginary_updates  # imagination (and MVE) on most steps


def test_an_agent_training_m_and_imagining_on_a_schedule_has_the_populations_losses():
    """M, r and d trained every 3rd real step and rollouts every 2nd (``model_every``,
    ``imagination_every``); C's N_I updates still every step."""
    config = agent_preset("fast", encoder="oracle", method="augmented", steps=90,
                          imagination_start=10, model_batch=32, model_every=3,
                          imagination_every=2)  # fmt: skip
    log = assert_same_run(config, OracleEncoder(config.oracle_sigma))
    assert count(log, "losses/mdn") == 30 * config.model_updates  # steps 0, 3, ..., 87
    assert count(log, "losses/reward") == 30 * (config.model_updates + config.reward_updates)
    imaginary = count(log, "losses/controller") - 90 * config.n_real_updates
    assert imaginary > 50 * config.n_imaginary_updates  # every step past I_start, not every 2nd


def test_the_baseline_has_the_populations_losses():
    """The `fast` baseline: the paper's C (no target network), no M, 300 steps."""
    config = agent_preset("fast", encoder="oracle", method="baseline", steps=300)
    log = assert_same_run(config, OracleEncoder(config.oracle_sigma))
    assert count(log, "losses/controller") == 300 and count(log, "losses/mdn") == 0


def test_an_agent_on_another_environment_has_the_populations_losses():
    """A Gymnasium environment (episodes seeded one by one), observed as a vector (sigma 0);
    the reference has no fallback (tests/test_fallback.py tests it), so it is off here."""
    config = agent_preset("fast", env="imagine-test/Line-v0", encoder="vector", steps=60,
                          imagination_start=2, model_batch=32, imagination_adaptive=False,
                          imagination_fallback=False)  # fmt: skip
    assert_same_run(config, VectorEncoder(2))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["augmented", "baseline"])
def test_the_fast_agents_have_the_populations_losses_over_400_steps(method):
    """The `fast` preset as it is (M's batches of 128, I_start at episode 100, near step 140)."""
    config = agent_preset("fast", encoder="oracle", method=method, steps=400)
    assert_same_run(config, OracleEncoder(config.oracle_sigma))


@pytest.mark.parametrize("setting", [{"imagination_adaptive": True},
                                     {"value_expansion_weighting": "steve"},
                                     {"imagination_draw": "outcome"}])  # fmt: skip
def test_what_the_reference_lacks_is_a_config_error(setting):
    config = agent_preset("fast", encoder="oracle", steps=1, **setting)
    with pytest.raises(ConfigError, match=f"agent.{next(iter(setting))} .* reference"):
        algorithm1.train(config, OracleEncoder())
