"""Issue 14's levers: M on V's means, imagination from M's mode, V's latent activity, the
linear probe and the learning-curve summary."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.evaluation import imagined_accuracy
from imagine.envs.gesture_puzzle.latent_classifier import LatentClassifier
from imagine.envs.gesture_puzzle.vision_report import latent_activity
from imagine.errors import ConfigError
from imagine.learning.gate import gate_transitions
from imagine.learning.imagination import imagine_rollouts
from imagine.models.controller import Controller, PopulationController
from imagine.models.world_model import PopulationWorldModel, WorldModel
from imagine.study.report import area_under_curve, curve_summary, first_reaching, where_paper_stood


def batch_of(n: int = 256, sigma: float = 0.5) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(n, 3, generator=g)
    action = torch.randint(6, (n,), generator=g)
    next_mu = mu + (action[:, None] == 0).float()
    single = {"mu": mu, "sigma": torch.full((n, 3), sigma), "action": action,
              "next_mu": next_mu, "next_sigma": torch.full((n, 3), sigma),
              "reward": torch.zeros(n), "done": torch.zeros(n)}  # fmt: skip
    return {k: v.unsqueeze(0) for k, v in single.items()}


def test_m_on_means_ignores_the_posterior_sigma():
    """model_latents=mu: M learns from V's means, so sigma (noise in collapsed dimensions)
    cannot reach its targets; with re-sampling it does."""
    losses = {}
    for sigma in (0.01, 3.0):
        for resample in (False, True):
            torch.manual_seed(0)
            model = PopulationWorldModel([WorldModel(3, dropout=0.0)])
            losses[(sigma, resample)] = model.update(
                batch_of(sigma=sigma), [torch.Generator().manual_seed(1)], resample=resample
            )["mdn"]
    assert torch.equal(losses[(0.01, False)], losses[(3.0, False)])
    assert not torch.equal(losses[(0.01, True)], losses[(3.0, True)])


def test_m_learns_a_known_transition_from_means_to_a_sharp_mode():
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(3, dropout=0.0)])
    batch, g = batch_of(sigma=0.9), [torch.Generator().manual_seed(1)]
    first = model.update(batch, g, resample=False)["mdn"]
    for _ in range(300):
        last = model.update(batch, g, resample=False)["mdn"]
    assert float(last[0]) < float(first[0]) - 3
    predicted = model.mode(batch["mu"][:, :64], batch["action"][:, :64])
    assert (predicted - batch["next_mu"][:, :64]).abs().mean() < 0.15


def test_population_mode_is_the_single_agent_most_likely_state():
    torch.manual_seed(0)
    models = [WorldModel(2, dropout=0.0) for _ in range(2)]
    population = PopulationWorldModel(models)
    z, a = torch.randn(2, 5, 2), torch.randint(6, (2, 5))
    mode = population.mode(z, a)
    for i in range(2):
        assert torch.allclose(mode[i], models[i].mdn.most_likely(z[i], a[i]), atol=1e-6)


def test_rollouts_from_the_mean_with_the_mode_are_deterministic():
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(4, dropout=0.0)])
    controller = PopulationController([Controller(4)])
    mu, sigma = torch.randn(1, 4), torch.zeros(1, 4)
    runs = [imagine_rollouts(model, controller, mu, sigma, 2, 3, [0.0],
                             [torch.Generator().manual_seed(s)], draw="mode")[0]
            for s in (0, 1)]  # fmt: skip
    first = runs[0]
    assert torch.equal(first["z"][0], mu[0]) and torch.equal(first["z"][1], mu[0])
    # the mode of M for the first step (computed alone, so up to the rounding of another batch)
    expected = model.mode(mu.view(1, 1, 4), first["action"][:1].view(1, 1))[0, 0]
    assert torch.allclose(first["next_z"][0], expected, atol=1e-6)
    assert all(torch.equal(runs[0][k], runs[1][k]) for k in first)


def test_bad_imagination_choices_are_refused():
    with pytest.raises(ConfigError, match="model_latents must be one of sample, mu"):
        agent_preset("fast", model_latents="means")
    with pytest.raises(ConfigError, match="imagination_draw must be one of sample, mode"):
        agent_preset("fast", imagination_draw="max")
    with pytest.raises(ConfigError, match="imagination_epsilon must be in"):
        agent_preset("fast", imagination_epsilon=1.5)
    with pytest.raises(ConfigError, match="reward_loss must be one of logcosh, mse"):
        agent_preset("fast", reward_loss="huber")
    with pytest.raises(ConfigError, match=r"reward_dropout must be in \[0, 1\) or null"):
        agent_preset("fast", reward_dropout=1.0)


def test_latent_activity_finds_the_collapsed_dimensions():
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(1000, 4, generator=g) * torch.tensor([1.0, 0.5, 0.05, 0.01])
    sigma = torch.tensor([0.1, 0.1, 0.9, 1.0]).expand(1000, 4)
    activity = latent_activity(mu, sigma)
    assert activity["collapsed_dimensions"] == [2, 3]
    assert activity["active_dimensions"] == 2
    kl = activity["kl_per_dimension"]
    assert kl[0] > 1.0 and kl[3] < 0.01
    assert kl[0] == pytest.approx(
        float((-0.5 * (1 + 2 * np.log(0.1) - mu[:, 0].square() - 0.01)).mean()), rel=1e-3
    )


def test_a_linear_probe_cannot_read_what_an_mlp_can():
    """Factor 'hand' laid out on a circle's radius: not linearly separable, an MLP reads it."""
    g = torch.Generator().manual_seed(0)
    states = torch.zeros(3000, 4, dtype=torch.int64)
    states[:, 3] = torch.randint(3, (3000,), generator=g)
    angle = torch.rand(3000, generator=g) * 2 * torch.pi
    radius = 1.0 + states[:, 3].float()
    z = torch.stack([radius * angle.cos(), radius * angle.sin()], -1)
    linear, mlp = LatentClassifier(2, hidden=0), LatentClassifier(2)
    linear.fit(z, states, steps=500, lr=3e-2)
    mlp.fit(z, states, steps=800)
    assert mlp.accuracy(z, states)["hand"] > 0.97
    assert linear.accuracy(z, states)["hand"] < 0.6


def test_learning_curve_summary():
    assert area_under_curve([0, 100, 300], [0.0, 50.0, 50.0]) == pytest.approx(
        (0.5 * 100 * 50 + 200 * 50) / 300
    )
    assert first_reaching([250, 500, 1000], [50.0, 91.0, 80.0], 90.0) == 500
    assert first_reaching([250, 500], [50.0, 60.0], 90.0) is None
    evaluations = [
        {"task": "hard", "method": m, "seed": s, "budget": b, "success": x / 100}
        for m, curve in (("baseline", (40, 80, 95)), ("augmented", (60, 95, 99)))
        for s in range(3)
        for b, x in zip((250, 500, 1000), curve, strict=True)
    ]
    rows = {r["method"]: r for r in curve_summary(evaluations)}
    assert rows["baseline"]["episodes_to_level"] == 1000
    assert rows["augmented"]["episodes_to_level"] == 500
    assert rows["augmented"]["auc_mean"] > rows["baseline"]["auc_mean"]
    assert rows["baseline"]["seeds_reaching_level"] == 3


def test_residual_m_starts_at_the_identity_and_matches_the_single_agent_form():
    torch.manual_seed(0)
    models = [WorldModel(3, dropout=0.0, residual=True) for _ in range(2)]
    for m in models:
        torch.nn.init.zeros_(m.mdn.mu_head.weight)
        torch.nn.init.zeros_(m.mdn.mu_head.bias)
    population = PopulationWorldModel(models)
    z, a = torch.randn(2, 4, 3), torch.randint(6, (2, 4))
    assert torch.equal(population.mode(z, a), z)  # no change predicted: the state stays
    assert torch.equal(models[0].mdn.most_likely(z[0], a[0]), z[0])
    g = torch.Generator().manual_seed(0)
    drawn = population.sample(z, a, [g, None])[0]
    expected = models[0].mdn.sample(z[0], a[0], torch.Generator().manual_seed(0))
    assert torch.allclose(drawn, expected, atol=1e-6)


def test_residual_m_carries_unchanged_factors_to_states_it_never_saw():
    """Action 0 adds 1 to every coordinate, the other actions leave the state as it is: trained
    on states near the origin, a residual M carries far states through the actions that leave
    them unchanged; a next-state M does not."""
    errors = {}
    for residual in (False, True):
        torch.manual_seed(0)
        model = PopulationWorldModel([WorldModel(3, dropout=0.0, residual=residual)])
        batch, g = batch_of(sigma=0.0), [torch.Generator().manual_seed(1)]
        for _ in range(400):
            model.update(batch, g, resample=False)
        far = torch.randn(1, 200, 3, generator=torch.Generator().manual_seed(2)) + 6.0
        action = torch.randint(6, (1, 200), generator=torch.Generator().manual_seed(3))
        truth = far + (action == 0).float().unsqueeze(-1)
        unchanged = action != 0
        errors[residual] = float((model.mode(far, action) - truth).abs()[unchanged].mean())
    assert errors[True] < 0.05 and errors[False] > 5 * errors[True]


class RuleModel:
    """An M in population form that knows the rules (the oracle embedding's dynamics), or,
    with ``frozen``, one that predicts that nothing changes."""

    def __init__(self, encoder, task: str, frozen: bool = False) -> None:
        self.encoder, self.task, self.frozen = encoder, task, frozen

    def _next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        from imagine.envs.gesture_puzzle.encoders import factored_embedding
        from imagine.envs.gesture_puzzle.rules import apply_actions

        if self.frozen:
            return z.clone()
        states = self.encoder.classify(z.reshape(-1, z.shape[-1])).numpy()
        nxt = apply_actions(states, action.reshape(-1).numpy())
        return factored_embedding(nxt).view(z.shape)

    def sample(self, z, action, generators):
        return self._next(z, action)

    def mode(self, z, action):
        return self._next(z, action)

    def predict(self, z, action, generators, draw):
        from imagine.models.world_model import Prediction

        return Prediction(self._next(z, action), torch.zeros(z.shape[:-1]))

    def _states(self, z):
        return self.encoder.classify(z.reshape(-1, z.shape[-1])).numpy()

    def is_terminal(self, z):
        from imagine.envs.gesture_puzzle.rules import is_terminal

        return torch.as_tensor(is_terminal(self._states(z), self.task)).view(z.shape[:-1])

    def predict_reward(self, z):
        from imagine.envs.gesture_puzzle.rules import rewards

        return torch.as_tensor(rewards(self._states(z), self.task), dtype=torch.float32).view(
            z.shape[:-1]
        )


def test_imagined_accuracy_judges_imagined_transitions_by_the_rules():
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.agent import Agent

    config = agent_preset("smoke", task="hard", encoder="oracle", imagination_draw="mode")
    encoder = OracleEncoder()
    torch.manual_seed(0)
    agent = Agent(config, encoder, Controller(8), WorldModel(8), 0, 0)
    exact = imagined_accuracy(agent, starts=20, model=RuleModel(encoder, "hard"))
    assert exact["state"] == exact["reward"] == exact["terminal"] == 1.0
    assert exact["transitions"] >= 20 * config.imagination_breadth
    frozen = imagined_accuracy(agent, starts=20, model=RuleModel(encoder, "hard", frozen=True))
    assert frozen["state"] == 0.0 and frozen["first_step"] == 0.0


def test_where_the_papers_baseline_stood():
    rows = [{"task": "hard", "method": "baseline", "budget": b, "mean": m, "n": 5}
            for b, m in ((250, 5.0), (1000, 31.0), (2000, 84.0))]  # fmt: skip
    (line,) = where_paper_stood(rows)
    assert "(30.1%)" in line and "by 1000 episodes" in line


def test_the_real_update_control_adds_real_updates_from_i_start_on(tmp_path):
    """The baseline's control for imagination: N_I extra real C updates from I_start, none
    before, and only for the baseline."""
    from imagine.learning.training import train
    from imagine.metrics import read_metrics

    config = agent_preset("smoke", encoder="oracle", method="baseline", episodes=60,
                          imagination_start=30, log_every=10,
                          real_in_place_of_imagined=True)  # fmt: skip
    train(config, tmp_path, threads=1)
    rows = read_metrics(tmp_path / "metrics.csv")
    extra = [r.get("losses/controller_real_extra") for r in rows]
    assert all(x is None or x != x for x in extra[:2])  # no extra updates before I_start
    assert all(x is not None and x == x for x in extra[-2:])  # every step after it
    with pytest.raises(ConfigError, match="control for method baseline"):
        agent_preset("fast", method="augmented", real_in_place_of_imagined=True)


def test_the_fast_agent_learns_thrice_from_imagination_per_step_and_its_control_from_real():
    """The `fast` preset's N_I = 3 (issue 14, round 14): past I_start each real step makes one
    C update on a real batch and three on imagined ones; the baseline's control for imagination
    makes its three in their place on real batches, and the plain baseline one update alone."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.population import Population

    def updates_per_step(**overrides) -> list[int]:
        config = agent_preset("fast", encoder="oracle", imagination_start=0, **overrides)
        population = Population([config], OracleEncoder())
        calls = []
        update = population.controller.update
        population.controller.update = lambda *a, **k: calls.append(1) or update(*a, **k)
        counts = []
        for _ in range(5):
            population._start_episodes()
            before = len(calls)
            population.step()
            counts.append(len(calls) - before)
        return counts

    assert agent_preset("fast").n_imaginary_updates == 3
    assert agent_preset("paper").n_imaginary_updates == 1  # the paper's one imaginary update
    assert updates_per_step() == [4] * 5
    assert updates_per_step(method="baseline", real_in_place_of_imagined=True) == [4] * 5
    assert updates_per_step(method="baseline") == [1] * 5


@pytest.mark.parametrize("start", ["current", "memory"])
def test_imagined_rollouts_start_where_imagination_from_says(start):
    """imagination_from=current: every rollout starts at the agent's current state (the paper);
    memory: at states of transitions in M_R (Dyna), not all of them the current one."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.population import Population

    config = agent_preset("smoke", encoder="oracle", method="augmented", imagination_start=0,
                          imagination_depth=1, imagination_breadth=4, model_latents="mu",
                          imagination_from=start)  # fmt: skip
    population = Population([config], OracleEncoder())
    currents, steps = [], 40
    for _ in range(steps):
        population._start_episodes()
        currents.append(population.mu[0].clone())
        population.step()
    imagined = population.imaginary.newest(4 * steps)["z"].view(steps, 4, -1)
    current = torch.stack(currents).unsqueeze(1)
    at_current = (imagined == current).all(-1)
    real = population.real.newest(steps)["mu"]
    in_memory = (imagined.view(-1, 1, real.shape[-1]) == real).all(-1).any(-1)
    assert bool(in_memory.all())
    if start == "current":
        assert bool(at_current.all())
    else:
        assert float(at_current.float().mean()) < 0.5


def test_macrostate_separation_measures_the_microstates_against_the_macrostates():
    from imagine.envs.gesture_puzzle.rules import all_macrostates
    from imagine.envs.gesture_puzzle.vision_report import macrostate_separation

    states = np.repeat(all_macrostates()[:4], 200, axis=0)  # 4 macrostates, 200 images each
    means = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 4.0], [2.0, 4.0]]).repeat_interleave(200, 0)
    g = torch.Generator().manual_seed(0)
    quiet = macrostate_separation(means + 0.05 * torch.randn(800, 2, generator=g), states)
    loud = macrostate_separation(means + 3.0 * torch.randn(800, 2, generator=g), states)
    assert quiet["nearest_macrostate_distance_min"] == pytest.approx(2.0, abs=0.05)
    assert quiet["within_std_per_dimension"] == pytest.approx([0.05, 0.05], abs=0.01)
    assert quiet["between_std_per_dimension"] == pytest.approx([1.155, 2.309], abs=0.02)
    assert quiet["separation_ratio"] > 20  # images sit on their macrostate's mean
    assert loud["separation_ratio"] < 1  # the microstate is louder than the macrostate


def test_a_diagonal_draw_leaks_from_clouds_whose_dimensions_move_together():
    """draw_accuracy: a perfect M's diagonal Gaussian drawn from two macrostates' clouds, read
    back by a classifier that reads every cloud point right. Round clouds: every draw right.
    Clouds stretched along y = x on either side of it (V's dimensions moving together from image
    to image): the diagonal Gaussian ignores the correlation and about half its draws cross; a
    mixture of five diagonal components follows the line and crosses far less."""
    from imagine.envs.gesture_puzzle.rules import all_macrostates
    from imagine.envs.gesture_puzzle.vision_report import draw_accuracy

    two = all_macrostates()[:2]
    states = np.repeat(two, 500, axis=0)
    side = torch.tensor([[0.2, -0.2], [-0.2, 0.2]]).repeat_interleave(500, 0)  # below / above

    def classify(z):  # below the line y = x: the first macrostate, above it: the second
        return torch.as_tensor(two[(z[:, 1] > z[:, 0]).long().numpy()])

    g = torch.Generator().manual_seed(0)
    round_clouds = 5 * side + 0.05 * torch.randn(1000, 2, generator=g)
    stretched = side + torch.randn(1000, 1, generator=g) * torch.tensor([1.0, 1.0])
    assert (classify(stretched).numpy() == states).all()  # the clouds themselves are read right
    assert draw_accuracy(round_clouds, states, classify) == {
        "scale_1": 1.0, "scale_0.5": 1.0, "components_5": 1.0}  # fmt: skip
    leaky = draw_accuracy(stretched, states, classify)
    assert 0.4 < leaky["scale_1"] < 0.7
    assert leaky["scale_1"] < leaky["scale_0.5"] < 0.9  # a lower temperature leaks less
    # five diagonal components share out each stretched cloud along its line: M's own form
    assert leaky["components_5"] > leaky["scale_0.5"]


@pytest.mark.parametrize("model", ["true", "true_mean"])
def test_a_true_model_imagines_every_transition_right_and_trains_m_anyway(model):
    """imagination_model=true (the diagnostic): imagination rolls out the rules through the
    encoder, so every transition in M_I is the true successor with the rules' reward and end,
    while M still learns from M_R; true_mean hands the successor's reference latent."""
    from imagine.config import agent_preset
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.envs.gesture_puzzle.rules import (
        apply_actions,
        is_terminal,
        macrostate_index,
        rewards,
    )
    from imagine.learning.population import Population

    config = agent_preset("smoke", encoder="oracle", method="augmented", imagination_start=0,
                          imagination_model=model, seed=1)  # fmt: skip
    encoder = OracleEncoder()
    p = Population([config], encoder)
    before = [w.clone() for w in p.model.parameters()]
    for _ in range(15):
        p.step()
    held = p.imaginary.size[0]
    data = {k: v[0, :held] for k, v in p.imaginary.data.items()}
    assert held > 0
    states = encoder.classify(data["z"]).numpy()
    truth = apply_actions(states, data["action"].numpy())
    assert (encoder.classify(data["next_z"]).numpy() == truth).all()
    assert data["reward"].numpy() == pytest.approx(rewards(truth, config.task))
    assert (data["done"].numpy() == is_terminal(truth, config.task)).all()
    assert any(not torch.equal(a, b) for a, b in zip(before, p.model.parameters(), strict=True))
    if model == "true_mean":
        means = encoder.state_latents()[torch.as_tensor(macrostate_index(truth))]
        assert torch.equal(data["next_z"], means)


def test_a_component_draw_keeps_the_heaviest_component_and_its_spread():
    """imagination_draw=component: M's most likely next macrostate, drawn with its spread; a
    draw by the weights lands in the light component now and then."""
    from imagine.models.world_model import Mixture, sample_mixture

    n = 4000
    log_pi = torch.log(torch.tensor([[0.3, 0.7]])).expand(n, 2)
    mu = torch.tensor([[[10.0, 10.0], [0.0, 0.0]]]).expand(n, 2, 2)
    mixture = Mixture(log_pi, mu, torch.full((n, 2, 2), 0.1))
    heaviest = sample_mixture(mixture, torch.Generator().manual_seed(0), "heaviest")
    weighted = sample_mixture(mixture, torch.Generator().manual_seed(0))
    assert heaviest.abs().max() < 1.0 and heaviest.std(0).numpy() == pytest.approx(
        [0.1] * 2, rel=0.1
    )
    assert (weighted[:, 0] > 5).float().mean().item() == pytest.approx(0.3, abs=0.03)
    torch.manual_seed(0)
    population = PopulationWorldModel([WorldModel(3, dropout=0.0) for _ in range(2)])
    z, a = torch.randn(2, 50, 3), torch.randint(6, (2, 50))
    gens = [torch.Generator().manual_seed(1), None]
    drawn = population.predict(z, a, gens, "component").next_z
    mode = population.mode(z, a)
    assert not torch.allclose(drawn[0], mode[0]) and torch.equal(drawn[1], torch.zeros(50, 3))


def test_an_outcome_draw_takes_each_component_by_its_weight_and_its_mean():
    """imagination_draw=outcome (a stochastic human's hand moves as often as M weighs it):
    the components' means, each as often as its weight, no Gaussian spread; through the
    population's predict, one row per agent as for the other draws."""
    from imagine.models.world_model import Mixture, sample_mixture

    n = 4000
    log_pi = torch.log(torch.tensor([[0.3, 0.7]])).expand(n, 2)
    mu = torch.tensor([[[10.0, 10.0], [0.0, 0.0]]]).expand(n, 2, 2)
    mixture = Mixture(log_pi, mu, torch.full((n, 2, 2), 0.1))
    outcome = sample_mixture(mixture, torch.Generator().manual_seed(0), spread=False)
    means = {tuple(row) for row in outcome.tolist()}
    assert means == {(10.0, 10.0), (0.0, 0.0)}
    assert (outcome[:, 0] > 5).float().mean().item() == pytest.approx(0.3, abs=0.03)
    torch.manual_seed(0)
    model = WorldModel(3, dropout=0.0, n_components=2)
    population = PopulationWorldModel([model])
    z, a = torch.randn(1, 2000, 3), torch.randint(6, (1, 2000))
    drawn = population.predict(z, a, [torch.Generator().manual_seed(1)], "outcome").next_z[0]
    with torch.no_grad():
        own = model.mdn(z[0], a[0])  # the agent's mixture, as its WorldModel computes it
    distance = (drawn[:, None, :] - own.mu).abs().max(-1).values  # (N, 2)
    assert (distance.min(-1).values < 1e-4).all()  # always one of the two means
    second = (distance[:, 1] < distance[:, 0]).float().mean().item()
    assert second == pytest.approx(own.log_pi.exp()[:, 1].mean().item(), abs=0.04)


def test_imagined_transitions_start_from_m_r_for_a_dyna_agent():
    """An agent that imagines from M_R (imagination_from=memory) is judged on rollouts from
    the states its M_R holds, as it imagines in training; others from new episodes' starts."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.envs.gesture_puzzle.evaluation import imagined_transitions
    from imagine.envs.gesture_puzzle.rules import all_macrostates, start_states
    from imagine.learning.agent import Agent

    encoder = OracleEncoder()
    held = all_macrostates()[[5, 17, 77]]  # terminal states: never a start of `hard`
    memory = (encoder.state_latents()[[5, 17, 77]], torch.zeros(3, dtype=torch.int64))
    config = agent_preset("smoke", task="hard", encoder="oracle", imagination_draw="mode")
    torch.manual_seed(0)
    nets = Controller(8), WorldModel(8)
    for start, expected in (("memory", held), ("current", start_states("hard"))):
        agent = Agent(replace(config, imagination_from=start), encoder, *nets, 0, 0, memory)
        rollout, _, _ = imagined_transitions(agent, 30, torch.Generator().manual_seed(0),
                                             RuleModel(encoder, "hard"))  # fmt: skip
        first = encoder.classify(rollout["z"][rollout["step"] == 0]).numpy()
        assert {tuple(s) for s in first} <= {tuple(s) for s in expected}


def test_split_models_take_the_state_from_one_m_and_the_reward_from_the_other():
    """true_reward: the learned M's next states with the rules' reward and end of whatever
    state it imagined; true_state: the rules' next states with the learned r and d."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.envs.gesture_puzzle.rules import (
        apply_actions,
        is_terminal,
        macrostate_index,
        rewards,
    )
    from imagine.learning.population import Population

    encoder = OracleEncoder()
    held = {}
    for model in ("true_reward", "true_state"):
        config = agent_preset("smoke", encoder="oracle", method="augmented", imagination_start=0,
                              imagination_model=model, imagination_draw="mode", seed=1)  # fmt: skip
        p = Population([config], encoder)
        for _ in range(15):
            p.step()
        n = p.imaginary.size[0]
        held[model] = data = {k: v[0, :n] for k, v in p.imaginary.data.items()}
        imagined = encoder.classify(data["next_z"]).numpy()
        if model == "true_reward":
            assert data["reward"].numpy() == pytest.approx(rewards(imagined, config.task))
            assert (data["done"].numpy() == is_terminal(imagined, config.task)).all()
        else:
            truth = apply_actions(encoder.classify(data["z"]).numpy(), data["action"].numpy())
            means = encoder.state_latents()[torch.as_tensor(macrostate_index(truth))]
            assert torch.equal(data["next_z"], means)
            # r has learned since the earlier steps: the newest transition is r's of now
            learned = p.model.predict_reward(data["next_z"][-1:].unsqueeze(0))[0]
            assert torch.allclose(data["reward"][-1:], learned)
            assert not np.isin(data["reward"].numpy(), [-1.0, -5.0, 50.0]).all()


def test_imagination_over_every_action_backs_up_each_start_through_m():
    """imagination_actions=all: from each of the I_B starts one step of every action, whatever
    C would choose and however deep I_D allows; each next state is M's mode for it."""
    torch.manual_seed(0)
    model = PopulationWorldModel([WorldModel(4, dropout=0.0)])
    controller = PopulationController([Controller(4)])
    mu, sigma = torch.randn(1, 3, 4), torch.zeros(1, 3, 4)
    out = imagine_rollouts(model, controller, mu, sigma, 3, 5, [0.0],
                           [torch.Generator().manual_seed(0)], draw="mode",
                           actions="all")[0]  # fmt: skip
    assert out["z"].shape == (3 * 6, 4)
    assert bool((out["step"] == 0).all())  # one step each, not I_D
    for b in range(3):
        mine = out["rollout"] // 6 == b  # start b's six one-step rollouts
        assert sorted(out["action"][mine].tolist()) == list(range(6))
        assert bool((out["z"][mine] == mu[0, b]).all())
    assert sorted(out["rollout"].tolist()) == list(range(3 * 6))  # each its own rollout
    # so a stop gate judges each (start, action) alone, as the mask does
    u = torch.rand(3 * 6, generator=torch.Generator().manual_seed(1))
    tau = torch.tensor(0.5)
    for rule in ("stop", "mask"):
        keep = gate_transitions(rule, u, out["rollout"], out["step"], tau, None)
        assert torch.equal(keep, u <= tau)
    expected = model.mode(out["z"].unsqueeze(0), out["action"].unsqueeze(0))[0]
    assert torch.allclose(out["next_z"], expected, atol=1e-6)
    with pytest.raises(ConfigError, match="imagination_actions must be one of policy, all"):
        agent_preset("fast", imagination_actions="some")


def test_an_agent_imagining_every_action_fills_its_imaginary_memory_with_them():
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.population import Population

    config = agent_preset("smoke", encoder="oracle", method="augmented", imagination_start=0,
                          imagination_breadth=2, imagination_from="memory",
                          imagination_actions="all")  # fmt: skip
    population = Population([config], OracleEncoder())
    for _ in range(3):
        population._start_episodes()
        population.step()
    assert int(population.imaginary.size[0]) == 3 * 2 * 6
    newest = population.imaginary.newest(12)
    assert sorted(newest["action"].tolist()) == sorted(list(range(6)) * 2)


def test_every_action_backups_switch_to_the_papers_rollouts_at_imagination_actions_until():
    """imagination_actions_until: before it, every action's one-step backups behind the gate;
    from it, the paper's policy rollouts, every transition kept; an agent on either side of
    the switch imagines in a population what it imagines alone in that setting."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.population import Population

    switching = agent_preset(
        "smoke", encoder="oracle", method="augmented", imagination_start=0,
        imagination_breadth=2, imagination_from="memory", imagination_actions="all",
        imagination_actions_until=5, imagination_gate="mask", imagination_uncertainty="support",
    )  # fmt: skip
    papers = replace(switching, imagination_actions="policy", imagination_actions_until=0,
                     imagination_gate="none", imagination_uncertainty="disagreement")  # fmt: skip
    every = replace(switching, imagination_actions_until=0)

    def imagine(configs, episodes):
        population = Population(configs, OracleEncoder())
        for _ in range(4):
            population.episode = list(episodes)  # agent 0 past the switch, agent 1 before it
            population.step()
        return population

    together = imagine([switching, replace(switching, seed=1)], [5, 0])
    after, before = imagine([papers], [5]), imagine([replace(every, seed=1)], [0])
    for agent, alone in ((0, after), (1, before)):
        held = int(together.imaginary.size[agent])
        assert held == int(alone.imaginary.size[0]) > 0
        for key, value in together.imaginary.data.items():
            assert torch.equal(value[agent, :held], alone.imaginary.data[key][0, :held]), key
    assert together._episode[0].accepted is None  # nothing gated after the switch
    assert together._episode[1].accepted is not None
    held = int(together.imaginary.size[1])
    assert held <= 4 * 2 * 6 and set(together.imaginary.data["action"][1, :held].tolist()) == set(
        range(6)
    )
    with pytest.raises(ConfigError, match="imagination_actions_until switches"):
        agent_preset("fast", imagination_actions_until=1000)
    with pytest.raises(ConfigError, match="imagination_actions_until must be >= 0"):
        agent_preset("fast", imagination_actions="all", imagination_actions_until=-1)


def test_an_agent_switched_to_the_papers_rollouts_keeps_its_n_i_under_the_adaptive_ratio():
    """With imagination_adaptive, N_I follows the gate's acceptance and M's trust; after
    imagination_actions_until the rollouts are ungated, so the agent makes the config's N_I
    (not a ratio frozen at its last gated step), even with an M never trusted."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.population import Population

    config = agent_preset(
        "smoke", encoder="oracle", method="augmented", imagination_start=0,
        imagination_actions="all", imagination_actions_until=5, imagination_gate="mask",
        imagination_uncertainty="support", imagination_adaptive=True,
        imagination_trust_floor=1.0, n_imaginary_updates=2,
    )  # fmt: skip

    def imaginary_updates(episode: int) -> int:
        population, made = Population([config], OracleEncoder()), []
        record = population._record

        def counting(key, loss, rows):
            made.append(key == "losses/controller_imaginary")
            record(key, loss, rows)

        population._record = counting
        for _ in range(4):
            population.episode = [episode]
            population.step()
        return sum(made)

    assert imaginary_updates(0) == 0  # gated, M not trusted: no imaginary update
    assert imaginary_updates(5) > 0  # switched: the config's N_I
