"""Population training: agents trained together have exactly the numbers they have alone."""

import dataclasses

import pytest
import torch
from torch import nn

from imagine.config import agent_preset
from imagine.errors import ConfigError
from imagine.learning.agent import load_agent
from imagine.learning.population import Population
from imagine.learning.training import train_population
from imagine.metrics import read_metrics
from imagine.models.stacked import PopulationAdam, StackedMLP, export_agent, set_matmul_dtype
from imagine.models.world_model import PopulationWorldModel, WorldModel


def numbers(folder):
    return [{k: v for k, v in row.items() if not k.startswith("time")}
            for row in read_metrics(folder / "metrics.csv")]  # fmt: skip


def assert_same_agent(a, b):
    assert (a.episode, a.t) == (b.episode, b.t)
    for module_a, module_b in ((a.controller, b.controller), (a.model, b.model)):
        for (name, p), q in zip(module_a.state_dict().items(), module_b.state_dict().values(),
                                strict=True):  # fmt: skip
            assert torch.equal(p, q), name


@pytest.mark.parametrize("overrides", [
    # smoke: the paper's 50% dropout in M, so dropout masks are per agent too; C's targets
    # expanded through M (the fast preset's MVE), so M's modes of each agent alone too
    {"belief": "filtered", "value_expansion": 2},
    # slow (make test-all): the same equality with the options' extra streams
    pytest.param({"target_update_period": 7, "double_dqn": True, "controller_input": "sample"},
                 marks=pytest.mark.slow),
    # members' bootstrap batches, dropout masks and draws per agent
    pytest.param({"model_ensemble": 2}, marks=pytest.mark.slow),
    # value expansion through the members' mean mode, per agent
    pytest.param({"model_ensemble": 2, "value_expansion": 2, "value_expansion_members": "mean"},
                 marks=pytest.mark.slow),
])  # fmt: skip
def test_agents_in_a_population_have_the_numbers_they_have_alone(tmp_path, overrides):
    settings = {"encoder": "oracle", "method": "augmented", "episodes": 200,
                "imagination_start": 60, "log_every": 10, "accuracy_every": 50,
                "checkpoint_every": 50, **overrides}  # fmt: skip
    seeds = (0, 1)  # agent 1 shares the stacked networks and memory with agent 0
    configs = [agent_preset("smoke", seed=s, **settings) for s in seeds]
    together = [tmp_path / f"together-{s}" for s in seeds]
    train_population(configs, together, threads=1)
    for config, folder in zip(configs, together, strict=True):
        alone = tmp_path / f"alone-{config.seed}"
        train_population([config], [alone], threads=1)
        assert numbers(folder) == numbers(alone)
        assert_same_agent(load_agent(folder), load_agent(alone))
    assert min(load_agent(f).t for f in together) >= 250, [load_agent(f).t for f in together]
    # the seeds really are different runs, each past I_start with imagination
    rows = [numbers(f)[-1] for f in together]
    assert len({r["charts/return"] for r in rows}) > 1
    assert all(r["charts/imagined_transitions"] > 0 for r in rows)


def test_a_population_resumes_agents_at_different_points(tmp_path):
    """Agents stopped at different episodes resume together and end as if never stopped."""
    settings = {"encoder": "oracle", "method": "augmented", "imagination_start": 30,
                "log_every": 10, "accuracy_every": 40, "checkpoint_every": 20}  # fmt: skip
    straight = [tmp_path / f"straight-{s}" for s in (0, 1)]
    resumed = [tmp_path / f"resumed-{s}" for s in (0, 1)]
    train_population([agent_preset("smoke", seed=s, episodes=100, **settings) for s in (0, 1)],
                     straight, threads=1)  # fmt: skip
    train_population([agent_preset("smoke", seed=0, episodes=40, **settings)], resumed[:1])
    train_population([agent_preset("smoke", seed=1, episodes=60, **settings)], resumed[1:])
    train_population([agent_preset("smoke", seed=s, episodes=100, **settings) for s in (0, 1)],
                     resumed, threads=1)  # fmt: skip
    for a, b in zip(straight, resumed, strict=True):
        assert numbers(a) == numbers(b)
        assert_same_agent(load_agent(a), load_agent(b))


def test_a_population_shares_everything_but_the_seed():
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder

    a = agent_preset("smoke", encoder="oracle", seed=0)
    with pytest.raises(ConfigError, match="only in their seed"):
        Population([a, dataclasses.replace(a, seed=1, model_lr=0.01)], OracleEncoder())


def test_stacked_mlp_computes_each_agents_own_network():
    torch.manual_seed(0)
    mlps = [nn.Sequential(nn.Linear(4, 16), nn.ReLU(), nn.Linear(16, 3)) for _ in range(3)]
    stacked = StackedMLP(mlps)
    x = torch.randn(3, 5, 4)
    out = stacked(x)
    for i, mlp in enumerate(mlps):
        assert torch.allclose(out[i], mlp(x[i]), atol=1e-6)
    copy = export_agent(stacked, 1, nn.Sequential(nn.Linear(4, 16), nn.ReLU(), nn.Linear(16, 3)))
    assert torch.allclose(copy(x[1]), out[1], atol=1e-6)


def fit_known_transition(matmul_dtype: str, updates: int = 300) -> tuple[dict, float]:
    """M of 2 agents after ``updates`` on a known transition (a shift of the latent plus a
    step per action; reward +50 and the end past a threshold), without dropout."""
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(8, dropout=0.0, reward_hidden=64) for _ in range(2)])
    set_matmul_dtype(model, matmul_dtype)
    generators = [torch.Generator().manual_seed(i) for i in range(2)]
    g = torch.Generator().manual_seed(5)
    z, action = torch.randn(2, 256, 8, generator=g), torch.randint(6, (2, 256), generator=g)
    next_z = z.roll(1, -1) + 0.5 * (action.unsqueeze(-1) - 2.5)
    goal = next_z[..., 0] > 1
    batch = {"mu": z, "sigma": torch.full_like(z, 0.01), "action": action, "next_mu": next_z,
             "next_sigma": torch.full_like(z, 0.01), "reward": torch.where(goal, 50.0, -1.0),
             "done": goal.float()}  # fmt: skip
    for _ in range(updates):
        losses = model.update(batch, generators, resample=False)
    assert {p.dtype for p in model.parameters()} == {torch.float32}
    assert {p.grad.dtype for p in model.parameters() if p.grad is not None} == {torch.float32}
    error = (model.mode(z, action) - next_z).abs().mean().item()
    return losses, error


def test_bfloat16_products_learn_a_known_transition_with_float32_weights_and_losses():
    """Mixed precision (``matmul_dtype: bfloat16``, issue 18): weights, gradients and losses
    stay float32, and M's log-likelihood (equation 5), r and d reach what float32 reaches."""
    full, full_error = fit_known_transition("float32")
    mixed, mixed_error = fit_known_transition("bfloat16")
    assert all(loss.dtype == torch.float32 for loss in mixed.values())
    assert (mixed["mdn"] < -8).all() and (full["mdn"] < -8).all(), (full, mixed)  # from ~ +10
    assert full_error < 0.15 and mixed_error < 1.5 * full_error, (full_error, mixed_error)
    assert (mixed["reward"] < 1.0).all() and (mixed["terminal"] < 0.01).all(), mixed
    torch.manual_seed(1)
    layer = StackedMLP([nn.Sequential(nn.Linear(8, 64)) for _ in range(2)]).layers[0]
    set_matmul_dtype(layer, "bfloat16")
    x = torch.randn(2, 5, 8)
    exact = torch.baddbmm(layer.bias.unsqueeze(1), x, layer.weight)
    assert layer(x).dtype == torch.float32 and not torch.equal(layer(x), exact)
    assert torch.allclose(layer(x), exact, rtol=0.05, atol=0.05)


def test_population_adam_is_torch_adam_per_agent_and_skips_agents():
    torch.manual_seed(0)
    mlps = [nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 1)) for _ in range(3)]
    references = [nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 1)) for _ in range(3)]
    for mlp, ref in zip(mlps, references, strict=True):
        ref.load_state_dict(mlp.state_dict())
    stacked = StackedMLP(mlps)
    optimizer = PopulationAdam(stacked.parameters(), 3, lr=0.01)
    ref_optimizers = [torch.optim.Adam(r.parameters(), lr=0.01, fused=True) for r in references]
    x, y = torch.randn(3, 16, 4), torch.randn(3, 16, 1)
    for step in range(5):
        agents = [0, 2] if step % 2 else [0, 1, 2]  # agent 1 sits out every other step
        optimizer.zero_grad()
        (stacked(x) - y).square().mean((1, 2))[agents].sum().backward()
        optimizer.step(agents)
        for i in agents:
            ref_optimizers[i].zero_grad()
            (references[i](x[i]) - y[i]).square().mean().backward()
            ref_optimizers[i].step()
    for i, ref in enumerate(references):
        trained = export_agent(stacked, i, nn.Sequential(nn.Linear(4, 8), nn.ReLU(),
                                                         nn.Linear(8, 1)))  # fmt: skip
        for p, q in zip(trained.parameters(), ref.parameters(), strict=True):
            assert torch.allclose(p, q, atol=1e-6)
    state = optimizer.agent_state(1, "optim")
    assert float(state["optim.0.step"]) == 3  # steps 0, 2, 4


def test_population_adam_hands_its_slices_to_torchs_fused_adam_exactly():
    # PopulationAdam.step calls torch's fused kernel directly; the same gradients stepped
    # through torch.optim.Adam itself (each chosen agent's slices given their gradient) must
    # give bitwise the same weights, moments and step counts, with agents sitting out
    torch.manual_seed(0)
    mlps = [nn.Sequential(nn.Linear(5, 24), nn.ReLU(), nn.Linear(24, 3)) for _ in range(4)]
    direct = StackedMLP(mlps)
    through_torch = StackedMLP(mlps)
    ours = PopulationAdam(direct.parameters(), 4, lr=0.003)
    theirs = PopulationAdam(through_torch.parameters(), 4, lr=0.003)
    for step in range(6):
        agents = [[0, 1, 2, 3], [1, 3], [0, 2, 3]][step % 3]
        grads = [torch.randn_like(p) for p in direct.parameters()]
        for p, q, g in zip(direct.parameters(), through_torch.parameters(), grads, strict=True):
            p.grad, q.grad = g.clone(), g.clone()
        ours.step(agents)
        for i, (rows, slices) in enumerate(zip(theirs.rows, theirs.slices, strict=True)):
            for (j, row), s in zip(rows, slices, strict=True):
                s.grad = theirs.params[j].grad[row] if i in agents else None
        theirs.optimizer.step()
    for p, q in zip(direct.parameters(), through_torch.parameters(), strict=True):
        assert torch.equal(p, q)
    for agent in range(4):
        a, b = ours.agent_state(agent, "o"), theirs.agent_state(agent, "o")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert float(ours.agent_state(1, "o")["o.0.step"]) == 4  # steps 0, 1, 3, 4


def test_dropout_masks_come_from_each_agents_generator_and_idle_agents_keep_every_unit():
    from imagine.models.stacked import agent_dropout

    x = torch.randn(3, 16, 40)
    gens = [torch.Generator().manual_seed(s) for s in (7, 8, 9)]
    out = agent_dropout(x, 0.25, [gens[0], None, gens[2]])
    for i in (0, 2):  # agent i's draws alone: kept where uniform < 0.75, scaled by 1 / 0.75
        keep = torch.rand(16, 40, generator=torch.Generator().manual_seed(7 + i)) < 0.75
        assert torch.equal(out[i], x[i] * (keep * (1 / 0.75)))
        assert not torch.equal(
            gens[i].get_state(), torch.Generator().manual_seed(7 + i).get_state()
        )
    assert torch.equal(out[1], x[1])  # agent 1 drew nothing and kept every unit
    assert torch.equal(gens[1].get_state(), torch.Generator().manual_seed(8).get_state())


def test_a_run_resumes_only_on_the_device_type_it_was_trained_on(tmp_path):
    import json

    from imagine.errors import CheckpointError

    config = agent_preset("smoke", encoder="oracle", episodes=20, imagination_start=10)
    train_population([config], [tmp_path / "run"], threads=1)
    meta = json.loads((tmp_path / "run" / "agent.json").read_text())
    assert meta["device"] == "cpu"
    meta["device"] = "cuda"  # as if trained on a GPU: its generator states are CUDA states
    (tmp_path / "run" / "agent.json").write_text(json.dumps(meta))
    longer = dataclasses.replace(config, episodes=30)
    with pytest.raises(CheckpointError, match="trained on cuda; resume it with --device cuda"):
        train_population([longer], [tmp_path / "run"], threads=1)


def test_auto_goes_where_imagine_auto_device_says(monkeypatch):
    from imagine.devices import resolve_device

    monkeypatch.setenv("IMAGINE_AUTO_DEVICE", "cpu")  # what the tests set: CPU arithmetic
    assert resolve_device("auto") == torch.device("cpu")
    monkeypatch.setenv("IMAGINE_AUTO_DEVICE", "tpu")
    with pytest.raises(ConfigError, match="unknown device 'tpu'"):
        resolve_device("auto")
    monkeypatch.delenv("IMAGINE_AUTO_DEVICE")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto") == torch.device(expected)
    assert resolve_device("cpu") == torch.device("cpu")  # an explicit device wins
