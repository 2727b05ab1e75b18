"""scripts/novelty_check.py: its oracle bound is the best a detector blind among the
never-visited pairs can do, and a randomized prior of beta 0 is the plain ensemble."""

from __future__ import annotations

import numpy as np
import torch

from imagine.envs.gesture_puzzle.evaluation import auroc
from imagine.models.world_model import PopulationWorldModel, WorldModel


def test_oracle_bound_beats_every_detector_blind_among_the_never_visited(load_script):
    novelty = load_script("novelty_check")
    rng = np.random.default_rng(0)
    seen = rng.integers(0, 4, 400)
    wrong = rng.random(400) < np.where(seen == 0, 0.55, 0.15)
    bound = novelty.oracle_bound(seen, wrong)
    for _ in range(200):  # any scores, tied on the never-visited
        scores = np.where(seen == 0, rng.normal(), rng.normal(size=400))
        assert auroc(scores, wrong) <= bound + 1e-12
    # the bound is reached: wrong visited above the never-visited above right visited
    best = np.where(seen == 0, 0.0, np.where(wrong, 1.0, -1.0))
    assert auroc(best, wrong) == bound


def test_a_prior_of_beta_zero_is_the_plain_ensemble(load_script):
    novelty = load_script("novelty_check")
    torch.manual_seed(0)
    model = WorldModel(8, ensemble=3, dropout=0.0, residual=True, reward_hidden=32)
    plain = PopulationWorldModel([model]).eval()
    with_prior = novelty.PriorWorldModel(model, 0.0, 1e-3, "logcosh").eval()
    z, action = torch.randn(1, 16, 8), torch.randint(0, 6, (1, 16))
    assert torch.equal(plain.member_modes(z, action), with_prior.member_modes(z, action))
    tilted = novelty.PriorWorldModel(model, 1.0, 1e-3, "logcosh").eval()
    modes = tilted.member_modes(z, action)
    assert not torch.allclose(modes, plain.member_modes(z, action))
    assert (modes[0, 0] - modes[0, 1]).abs().max() > 1e-3  # members' priors differ


def test_the_stacked_combiner_learns_which_signal_carries_the_labels(load_script):
    """Leave one run out: weights fitted on runs where only the second signal tells the wrong
    transitions score each held-out run as that signal does."""
    novelty = load_script("novelty_check")
    rng = np.random.default_rng(0)
    ranks, wrong = [], []
    for _ in range(3):
        x = rng.random((300, 3))
        wrong.append(rng.random(300) < x[:, 1])  # the second signal is the error's probability
        ranks.append(x)
    weights = novelty.logistic_fit(np.concatenate(ranks), np.concatenate(wrong).astype(float))
    assert weights[1] > 2.0 and abs(weights[0]) < 1.0 and abs(weights[2]) < 1.0
    held_out = novelty.stacked_aurocs(ranks, wrong, products=False)
    alone = np.array([auroc(r[:, 1], w) for r, w in zip(ranks, wrong, strict=True)])
    assert np.allclose(held_out, alone, atol=0.02)
    assert novelty.stack_features(ranks[0], products=True).shape == (300, 6)


def test_fit_is_ms_error_at_the_nearest_real_start_with_the_same_action(load_script):
    from types import SimpleNamespace

    novelty = load_script("novelty_check")
    torch.manual_seed(0)
    model = WorldModel(8, ensemble=2, dropout=0.0, residual=True, reward_hidden=32).eval()
    mu = torch.stack([torch.zeros(8), torch.full((8,), 5.0), torch.full((8,), 0.1)])
    action = torch.tensor([1, 1, 2])  # the third start is nearest z = 0 but has another action
    with torch.no_grad():
        predicted = model.most_likely(mu, action)
    shift = torch.zeros(3, 8)
    shift[0, 0] = 3.0  # M is off by 3 at the first start, exact at the others
    next_mu = predicted + shift
    r = {"z": torch.stack([torch.full((8,), 0.05), torch.full((8,), 4.9)]),
         "action": torch.tensor([1, 1])}  # fmt: skip
    fit = novelty.fit_error(SimpleNamespace(model=model), r, mu, action, next_mu)
    assert np.allclose(fit, [3.0, 0.0], atol=1e-5)


def test_jitter_is_how_far_ms_prediction_moves_with_its_start(load_script):
    """An M that ignores z does not move; one that copies z moves by the noise it is given,
    in proportion to the fraction of M_R's spread."""
    from types import SimpleNamespace

    novelty = load_script("novelty_check")

    class Copy:
        def eval(self):
            return self

        def most_likely(self, z, action):
            return z * torch.tensor(1.0 if self.moves else 0.0)

    memory_mu = torch.randn(500, 8, generator=torch.Generator().manual_seed(1)) * 2.0
    r = {"z": torch.randn(40, 8), "action": torch.randint(0, 6, (40,))}
    still, copy = Copy(), Copy()
    still.moves, copy.moves = False, True
    assert np.allclose(novelty.jitter(SimpleNamespace(model=still), r, memory_mu, 0.3), 0.0)
    small = novelty.jitter(SimpleNamespace(model=copy), r, memory_mu, 0.1)
    large = novelty.jitter(SimpleNamespace(model=copy), r, memory_mu, 0.3)
    assert np.allclose(large, 3 * small, rtol=1e-4)  # the same draws, three times the scale
    # E||s eps|| for eps ~ N(0, I_8) is about s sqrt(8) with s = 0.1 x 2
    assert 0.4 < small.mean() < 0.7


def test_bagged_members_each_draw_only_from_their_own_share(load_script):
    from imagine.learning.memory import ReplayMemory, real_fields

    novelty = load_script("novelty_check")
    memory = ReplayMemory(400, real_fields(4))
    n = 400
    memory.add(mu=torch.arange(n, dtype=torch.float32)[:, None].expand(n, 4).clone(),
               sigma=torch.ones(n, 4), action=torch.zeros(n, dtype=torch.int64),
               next_mu=torch.zeros(n, 4), next_sigma=torch.ones(n, 4), reward=torch.zeros(n),
               done=torch.zeros(n))  # fmt: skip
    sample = novelty.member_batches(memory, 0.5, 3, 64, torch.Generator().manual_seed(0))
    seen = [set() for _ in range(3)]
    for _ in range(50):
        batch = sample()
        assert batch["mu"].shape == (1, 3 * 64, 4)
        for k in range(3):  # member k's batch is the k-th block of 64
            seen[k] |= set(batch["mu"][0, 64 * k : 64 * (k + 1), 0].long().tolist())
    for k in range(3):
        assert 150 < len(seen[k]) < 250  # about half of the 400, and only those
    assert seen[0] != seen[1]  # each member its own share
