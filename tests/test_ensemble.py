"""Issue 15: M as an ensemble of K MDNs per agent, its members' disagreement, and that
disagreement as a detector of wrong imagined transitions."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.evaluation import auroc, disagreement_detection, imagined_accuracy
from imagine.errors import ConfigError
from imagine.learning.agent import load_agent
from imagine.learning.agent_checkpoint import load_checkpoint
from imagine.learning.imagination import imagine_rollouts, posterior_scale
from imagine.learning.population import Population
from imagine.learning.training import train_population
from imagine.metrics import read_metrics
from imagine.models.controller import Controller, PopulationController
from imagine.models.world_model import PopulationWorldModel, WorldModel, members_spread


def batch_of(n: int, d: int = 3, agents: int = 1, seed: int = 0) -> dict[str, torch.Tensor]:
    """A known transition (action 0 adds 1 to every coordinate), terminal where z_0 > 1."""
    g = torch.Generator().manual_seed(seed)
    mu = torch.randn(agents, n, d, generator=g)
    action = torch.randint(6, (agents, n), generator=g)
    next_mu = mu + (action[..., None] == 0).float()
    return {"mu": mu, "sigma": torch.full_like(mu, 0.1), "action": action, "next_mu": next_mu,
            "next_sigma": torch.full_like(mu, 0.1), "reward": -next_mu[..., 0],
            "done": (next_mu[..., 0] > 1).float()}  # fmt: skip


def numbers(folder):
    return [{k: v for k, v in row.items() if not k.startswith("time")}
            for row in read_metrics(folder / "metrics.csv")]  # fmt: skip


def weights(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in module.parameters()])


def test_bad_ensemble_sizes_are_refused_in_one_line():
    with pytest.raises(ConfigError) as error:
        agent_preset("fast", model_ensemble=0)
    assert str(error.value) == "agent.model_ensemble must be positive, got 0"
    assert agent_preset("paper").model_ensemble == 1  # the paper's single MDN


def test_one_member_is_the_m_it_always_was_and_member_0_starts_as_it():
    """K = 1: the state dict of before (old checkpoints load); K = 3: member 0, r and d are
    initialized as the one-member M's, members 1 and 2 on their own."""
    torch.manual_seed(0)
    one = WorldModel(4, dropout=0.0)
    torch.manual_seed(0)
    three = WorldModel(4, dropout=0.0, ensemble=3)
    assert all(k.split(".")[0] in ("mdn", "reward", "terminal") for k in one.state_dict())
    assert len(one.members) == 1 and len(three.members) == 3
    for name, value in one.state_dict().items():
        assert torch.equal(three.state_dict()[name], value), name
    a, b, c = (weights(m) for m in three.members)
    assert not torch.equal(a, b) and not torch.equal(b, c)


def test_member_0_learns_as_the_one_member_m_on_the_same_first_batch():
    """Members are independent networks: adding members, each on its own bootstrap batch,
    changes nothing for member 0, r and d, which learn from the first batch."""
    B = 32
    batch = batch_of(3 * B)
    first = {name: v[:, :B] for name, v in batch.items()}
    trained = {}
    for k, data in ((1, first), (3, batch)):
        torch.manual_seed(0)
        model = PopulationWorldModel([WorldModel(3, dropout=0.0, ensemble=k)])
        for _ in range(5):
            losses = model.update(data, [torch.Generator()], resample=False)
        assert losses["mdn"].shape == (1,)
        trained[k] = model.export_agent(0, WorldModel(3, ensemble=k))
    for part in ("mdn", "reward", "terminal"):
        assert torch.equal(weights(getattr(trained[1], part)), weights(getattr(trained[3], part)))


def test_identical_members_part_on_their_own_bootstrap_batches():
    torch.manual_seed(0)
    model = WorldModel(3, dropout=0.0, ensemble=3)
    for member in model.more_mdns:
        member.load_state_dict(model.mdn.state_dict())
    population = PopulationWorldModel([model])
    z, a = torch.randn(1, 16, 3), torch.randint(6, (1, 16))
    assert torch.equal(members_spread(population.member_modes(z, a)), torch.zeros(1, 16))
    batch = batch_of(3 * 64)
    for _ in range(3):
        population.update(batch, [torch.Generator().manual_seed(1)], resample=False)
    trained = population.export_agent(0, WorldModel(3, ensemble=3))
    w0, w1, w2 = (weights(m) for m in trained.members)
    assert not torch.equal(w0, w1) and not torch.equal(w1, w2) and not torch.equal(w0, w2)
    assert bool((members_spread(population.member_modes(z, a)) > 0).all())


def test_each_member_in_a_population_computes_and_learns_what_it_does_alone():
    """P = 2 agents x K = 2 members: each member's modes are its own MDN's, and its update is
    torch Adam on its own loss over its own bootstrap batch."""
    torch.manual_seed(0)
    P, K, B = 2, 2, 16
    models = [WorldModel(3, dropout=0.0, ensemble=K) for _ in range(P)]
    references = [WorldModel(3, dropout=0.0, ensemble=K) for _ in range(P)]
    for model, ref in zip(models, references, strict=True):
        ref.load_state_dict(model.state_dict())
    population = PopulationWorldModel(models, lr=1e-3)
    z, a = torch.randn(P, 5, 3), torch.randint(6, (P, 5))
    modes = population.member_modes(z, a)
    for i in range(P):
        for k, mdn in enumerate(models[i].members):
            assert torch.allclose(modes[i, k], mdn.most_likely(z[i], a[i]), atol=1e-6)
    batch = batch_of(K * B, agents=P)
    optimizers = [torch.optim.Adam(r.parameters(), lr=1e-3, fused=True) for r in references]

    def own_loss(i: int, ref: WorldModel) -> torch.Tensor:
        """Agent i's losses alone: member k on rows [kB, (k+1)B), r and d on the first B."""
        rows = [slice(k * B, (k + 1) * B) for k in range(K)]
        mu, action, next_mu = batch["mu"][i], batch["action"][i], batch["next_mu"][i]
        mdn = sum(
            m.loss(mu[r], action[r], next_mu[r]) for m, r in zip(ref.members, rows, strict=True)
        )
        reward = ref.reward.loss(next_mu[rows[0]], batch["reward"][i, rows[0]])
        return mdn + reward + ref.terminal.loss(next_mu[rows[0]], batch["done"][i, rows[0]])

    for _ in range(3):
        population.update(batch, [torch.Generator(), torch.Generator()], resample=False)
        for i, (ref, optimizer) in enumerate(zip(references, optimizers, strict=True)):
            optimizer.zero_grad()
            own_loss(i, ref).backward()
            optimizer.step()
    # gradients agree to ~1e-9; Adam turns a near-zero gradient's rounding into a step of up
    # to lr, so weights are compared at lr 1e-3 to 1e-5
    for i, ref in enumerate(references):
        trained = population.export_agent(i, WorldModel(3, ensemble=K))
        for (name, p), q in zip(trained.state_dict().items(), ref.state_dict().values(),
                                strict=True):  # fmt: skip
            assert torch.allclose(p, q, atol=1e-5), name


def test_disagreement_is_zero_for_agreeing_members_and_grows_with_a_perturbation():
    torch.manual_seed(0)
    model = WorldModel(3, dropout=0.0, ensemble=3)
    for member in model.more_mdns:
        member.load_state_dict(model.mdn.state_dict())
    z, a = torch.randn(1, 8, 3), torch.randint(6, (1, 8))
    gens = [torch.Generator().manual_seed(0)]
    spreads = []
    for shift in (0.0, 0.1, 1.0):
        with torch.no_grad():
            perturbed = WorldModel(3, dropout=0.0, ensemble=3)
            perturbed.load_state_dict(model.state_dict())
            perturbed.more_mdns[1].mu_head.bias += shift  # every component's mean moves
        spreads.append(PopulationWorldModel([perturbed]).predict(z, a, gens, "mode").spread)
    assert torch.equal(spreads[0], torch.zeros(1, 8))
    assert bool((spreads[1] > 0).all()) and bool((spreads[2] > 5 * spreads[1]).all())
    # one member of three shifted by 1 in each of 3 dimensions: 4 of the 6 ordered pairs are
    # sqrt(3) apart, 2 are 0 apart
    assert torch.allclose(spreads[2], torch.full((1, 8), 4 / 6 * math.sqrt(3)), atol=1e-5)
    one = PopulationWorldModel([WorldModel(3, dropout=0.0)])
    assert torch.equal(one.predict(z, a, gens, "sample").spread, torch.zeros(1, 8))


def test_rollouts_follow_a_member_per_step_and_carry_scaled_disagreement():
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(4, dropout=0.0, ensemble=3)])
    controller = PopulationController([Controller(4)])
    mu = torch.randn(1, 4)
    sigma = torch.tensor([[0.1, 0.3, 0.95, 1.0]])  # two active dimensions, mean sigma 0.2
    assert torch.allclose(posterior_scale(sigma), torch.tensor([0.2]))
    rollout = imagine_rollouts(model, controller, mu, sigma, 64, 1, [0.0],
                               [torch.Generator().manual_seed(0)], draw="mode")[0]  # fmt: skip
    z, action = rollout["z"].unsqueeze(0), rollout["action"].unsqueeze(0)
    modes = model.member_modes(z, action)[0]  # (K, N, D)
    assert torch.allclose(rollout["disagreement"], members_spread(modes) / 0.2, atol=1e-5)
    followed = (modes == rollout["next_z"]).all(-1)  # which member each transition followed
    assert bool(followed.any(0).all()) and bool(followed.any(1).all())  # each of the three used


def test_auroc_by_ranks():
    scores = np.array([0.1, 0.2, 0.8, 0.9])
    assert auroc(scores, np.array([False, False, True, True])) == 1.0
    assert auroc(scores, np.array([True, True, False, False])) == 0.0
    assert auroc(np.ones(4), np.array([True, False, True, False])) == 0.5
    assert auroc(np.array([1, 2, 3, 4]), np.array([False, True, False, True])) == 0.75
    assert math.isnan(auroc(scores, np.ones(4, dtype=bool)))


def test_disagreement_detection_splits_at_the_median():
    disagreement = np.array([0.3, 0.0, 6.0, 0.2, 5.0, 0.1])
    right = np.array([True, True, False, False, False, True])
    out = disagreement_detection(disagreement, right)
    # wrong ones score 0.2, 5 and 6: above 2, 3 and 3 of the 3 right ones
    assert out["disagreement_auroc"] == pytest.approx(8 / 9)
    assert out["state_agreed_half"] == pytest.approx(2 / 3)  # 0.0, 0.1, 0.2
    assert out["state_disagreed_half"] == pytest.approx(1 / 3)  # 0.3, 5, 6


@pytest.fixture(scope="module")
def ensemble_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ensemble") / "run"
    config = agent_preset("smoke", encoder="oracle", method="augmented", episodes=30,
                          imagination_start=10, log_every=10, checkpoint_every=10,
                          accuracy_every=10, model_ensemble=3)  # fmt: skip
    train_population([config], [folder], threads=1)
    return config, folder


def test_an_ensemble_agent_saves_loads_and_resumes_as_if_never_stopped(ensemble_run, tmp_path):
    config, straight = ensemble_run
    agent = load_agent(straight)
    assert len(agent.model.members) == 3
    population = Population([config], agent.encoder)
    load_checkpoint(population, 0, straight)
    _, model = population.networks(0)
    for (name, p), q in zip(model.state_dict().items(), agent.model.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(p, q), name
    resumed = tmp_path / "resumed"
    train_population([dataclasses.replace(config, episodes=20)], [resumed], threads=1)
    train_population([config], [resumed], threads=1)
    again = load_agent(resumed)
    for (name, p), q in zip(again.model.state_dict().items(), agent.model.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(p, q), name
    assert numbers(resumed) == numbers(straight)
    assert all(row["charts/imagined_disagreement"] > 0 for row in numbers(straight)[1:])


def test_evaluate_reports_the_disagreement_auroc(ensemble_run, capsys):
    from imagine.cli import evaluate_agent

    _, folder = ensemble_run
    agent = load_agent(folder)
    imagined = imagined_accuracy(agent, starts=20)
    n = int(imagined["transitions"])
    agreed, rest = n // 2 * imagined["state_agreed_half"], (n - n // 2) * imagined[
        "state_disagreed_half"]  # fmt: skip
    assert imagined["state"] == pytest.approx((agreed + rest) / n)
    assert imagined["disagreement_mean"] > 0
    evaluate_agent(folder, episodes=10, seed=0)
    written = json.loads((folder / "evaluation.json").read_text())
    assert written["imagined_disagreement_auroc"] == written["imagined_accuracy"][
        "disagreement_auroc"]  # fmt: skip
    assert "members as a detector of wrong imagined states: AUROC" in capsys.readouterr().out


def test_disagreement_from_m_r_starts_is_in_units_of_v_posterior_scale(ensemble_run, monkeypatch):
    """M_R's sigma is not in the checkpoint: the disagreement of rollouts from its states is
    still in V's posterior scale (the oracle's 0.05), not divided by the floor 1e-6, so the
    reported gate threshold is in the unit training used."""
    from imagine.envs.gesture_puzzle import evaluation

    config, folder = ensemble_run
    agent = load_agent(folder)
    agent.config = dataclasses.replace(config, imagination_from="memory")
    assert agent.memory_starts is not None
    seen = []
    real = evaluation.imagine_rollouts

    def spy(*args, **kwargs):
        seen.append(kwargs["scale"])
        return real(*args, **kwargs)

    monkeypatch.setattr(evaluation, "imagine_rollouts", spy)
    out = imagined_accuracy(agent, starts=12)
    assert torch.allclose(seen[0], torch.full_like(seen[0], 0.05))
    assert 0 < out["gate_threshold"] < 1e3


def test_an_ensembles_prediction_is_its_members_mean_mode_and_one_member_is_its_mdn():
    """M's point prediction (accuracy, generalization, planning): one MDN's most likely next
    state for K = 1, bitwise; the mean of the K members' modes for an ensemble, which differs
    from any one member's when the members differ."""
    torch.manual_seed(0)
    z, a = torch.randn(7, 3), torch.randint(6, (7,))
    single = WorldModel(3, ensemble=1).eval()
    assert torch.equal(single.most_likely(z, a), single.mdn.most_likely(z, a))
    ensemble = WorldModel(3, ensemble=3).eval()
    modes = torch.stack([mdn.most_likely(z, a) for mdn in ensemble.members])
    mean = ensemble.most_likely(z, a)
    assert torch.allclose(mean, modes.mean(0))
    assert not torch.allclose(mean, modes[0])
