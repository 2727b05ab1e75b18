"""model_scales: the MDN's scales fitted on the network without dropout's masks (issue 14)."""

import pytest
import torch

from imagine.config import AgentConfig, ConfigError
from imagine.models.world_model import MDN, PopulationWorldModel, WorldModel

NOISE = 0.05


def linear_batch(n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """z' = z rotated by the action's sign plus N(0, NOISE^2) noise: one outcome per (z, a)."""
    mu = torch.randn(1, n, 4, generator=generator)
    action = torch.randint(2, (1, n), generator=generator)
    sign = (1.0 - 2.0 * action).unsqueeze(-1)
    next_mu = sign * mu.roll(1, -1) + NOISE * torch.randn(1, n, 4, generator=generator)
    zeros = torch.zeros(1, n)
    return {"mu": mu, "sigma": torch.zeros_like(mu), "action": action, "next_mu": next_mu,
            "next_sigma": torch.zeros_like(mu), "reward": zeros, "done": zeros}  # fmt: skip


def train(scales: str, updates: int, dropout: float = 0.5) -> PopulationWorldModel:
    torch.manual_seed(0)
    model = WorldModel(latent_dim=4, n_actions=2, dropout=dropout, reward_hidden=16,
                       scales=scales)  # fmt: skip
    population = PopulationWorldModel([model])
    data, masks = torch.Generator().manual_seed(1), [torch.Generator().manual_seed(2)]
    for _ in range(updates):
        population.update(linear_batch(256, data), masks, resample=False)
    return population


@torch.no_grad()
def heaviest(population: PopulationWorldModel) -> tuple[float, float]:
    """The mask-free M's scale of its heaviest component (mean over dimensions and test
    inputs) and the root mean square error of its mean."""
    test = linear_batch(1024, torch.Generator().manual_seed(9))
    m = population._mixture(population._heads(test["mu"], test["action"]), test["mu"])
    k = m.log_pi.argmax(-1)[..., None, None].expand(1, 1024, 1, 4)
    sigma, mu = m.sigma.gather(-2, k).squeeze(-2), m.mu.gather(-2, k).squeeze(-2)
    return float(sigma.mean()), float((mu - test["next_mu"]).square().mean().sqrt())


def test_clean_scales_match_the_predicting_networks_error_and_dropout_scales_are_wider():
    """With dropout's masks the scales also cover the masks' jitter of the means, so the
    mask-free M predicts scales far wider than its own error; the clean heads fit that error."""
    dropout_sigma, dropout_error = heaviest(train("dropout", 300))
    clean_sigma, clean_error = heaviest(train("clean", 300))
    assert clean_error == pytest.approx(dropout_error)  # the same means (below)
    assert dropout_sigma > 1.5 * dropout_error
    assert clean_sigma == pytest.approx(clean_error, rel=0.3)


def test_clean_scales_leave_the_means_and_weights_bitwise_as_they_were():
    """The clean heads are copies (no random draw) trained on their own loss alone: every other
    parameter of M, and so its modes, are those of the paper's fit."""
    paper, clean = train("dropout", 30, dropout=0.2), train("clean", 30, dropout=0.2)
    shared = dict(clean.named_parameters())
    for name, p in paper.named_parameters():
        assert torch.equal(p, shared.pop(name)), name
    assert set(shared) == {"mdn.clean_sigma_head.weight", "mdn.clean_sigma_head.bias"}
    assert not torch.equal(shared["mdn.clean_sigma_head.weight"], paper.mdn.sigma_head.weight)


def test_the_clean_loss_trains_only_the_clean_heads():
    torch.manual_seed(0)
    population = PopulationWorldModel([WorldModel(4, n_actions=2, dropout=0.5, scales="clean")])
    batch = linear_batch(64, torch.Generator().manual_seed(0))
    population._clean_scale_nll(batch["mu"], batch["action"], batch["next_mu"]).sum().backward()
    moved = {name for name, p in population.mdn.named_parameters()
             if p.grad is not None and p.grad.abs().sum() > 0}  # fmt: skip
    assert moved == {"clean_sigma_head.weight", "clean_sigma_head.bias"}


def test_an_exported_mdn_predicts_with_the_clean_heads_in_eval_mode_only():
    """A single agent's MDN: in training mode (masks on) the masked network's scales, in eval
    mode the clean ones; the full covariance's factors likewise."""
    population = train("clean", 20, dropout=0.2)
    model = population.export_agent(
        0, WorldModel(latent_dim=4, n_actions=2, dropout=0.2, reward_hidden=16, scales="clean")
    )
    mdn = model.mdn.eval()
    z, a = torch.randn(8, 4), torch.randint(2, (8,))
    heads = population.mdn(torch.cat([z, torch.nn.functional.one_hot(a, 2).float()], -1)[None])
    assert torch.allclose(mdn(z, a).sigma, population._mixture(heads, z[None]).sigma[0])
    h = mdn.body(torch.cat([z, torch.nn.functional.one_hot(a, 2).float()], -1))
    assert not torch.allclose(mdn(z, a).sigma.flatten(1), mdn.sigma_head(h))
    full = MDN(4, n_actions=2, covariance="full", clean_scales=True)
    assert {"clean_sigma_head.weight", "clean_tril_head.weight"} <= set(full.state_dict())


def test_a_clean_scales_agent_trains_saves_and_loads(smoke_agent):
    _, agent = smoke_agent(model_scales="clean")
    mdn = agent.model.mdn
    assert agent.config.model_scales == "clean" and not mdn.training
    assert not torch.equal(mdn.clean_sigma_head.weight, mdn.sigma_head.weight)  # learned apart


def test_a_bad_scale_fit_is_a_config_error():
    with pytest.raises(ConfigError, match="model_scales"):
        AgentConfig(model_scales="wide")
    with pytest.raises(ValueError, match="scales"):
        WorldModel(4, scales="wide")
