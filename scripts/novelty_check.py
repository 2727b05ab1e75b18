"""How much of M's early error is novelty, and can any detector of it reach issue 15's AUROC?

For each agent run given (issue 15's early regime: an augmented agent at 250 episodes, where
8-56% of imagined transitions are wrong), the transitions imagination hands C as
``imagine evaluate`` makes them, judged by V's latent classifier (which the agent never uses).
Each is given its *visits*: how many real transitions of the agent's M_R start in the same
macrostate (read by the same classifier) with the same action, i.e. how often M has seen this
(state, action) pair. Prints, pooled over the runs, the share of transitions and how often
they are wrong per number of visits, and per run the AUROC as a detector of the wrong ones of:

- disagreement: the K members' mean pairwise distance between modes (the `fast` gate's u);
- support: the distance from (z, a) to the nearest real start with action a (label-free
  novelty, :func:`imagine.learning.gate.support_distance`);
- lookup: the distance from M's next state to what the nearest real transition with the
  same action says it is (`scripts/uncertainty_check.py`), a non-parametric model's
  disagreement with M;
- fit: M's own error where it has data: ||M(mu_j, a) - next_mu_j|| for the real transition j
  with the same action whose start mu_j is nearest z (M's point prediction, the members' mean
  mode): how well M has learned the (state, action) pair it is asked about, a pair seen once
  and not yet fitted showing a large error;
- cycle: ||z' - E(D(z'))||, how far V moves M's next state when its decoder draws it and its
  encoder reads the drawing back (`scripts/uncertainty_check.py`);
- jitter: how far M's point prediction moves when its start moves as another image of the
  same state would, mean_n ||M(z + s * eps_n, a) - M(z, a)|| over 8 draws eps_n ~ N(0, I),
  s a fraction (``--jitter``, 0.3) of the per-dimension spread of M_R's start mu: a pair M
  has seen on one image only may be right there and wrong on the pair's other images;
- sums of ranks: disagreement's rank + support's rank, support's + lookup's, all three
  (and how often the half of the transitions with the lowest sum of all three is right: what a
  gate accepting half would keep), and all five;
- visits (oracle): minus the visit count, a perfect novelty detector (it uses the labels);
- oracle bound: the best AUROC of a detector that orders the visited transitions perfectly
  (every wrong one above every right one) but cannot tell M's right guesses from its wrong
  ones on never-visited pairs (ties): the never-visited placed between the two;
- the AUROC of disagreement and support *within* the never-visited pairs.

``--stack``: can weights do better than the sum of ranks? The signals' within-run ranks
(scaled to [0, 1]) are combined by a logistic regression fitted on the other runs' transitions
and their labels, and judged on the run left out (leave one run out): fixed weights, learned
once from a study, would be label-free where they are used. Also with the pairwise products
of the ranks as features; with the first three signals, all five, the three with jitter,
and all six.

``--priors B1,B2,...``: also train fresh K-member ensembles on each run's real memory (the
agent's networks, batches and number of updates, but all on the final M_R rather than online)
with a *randomized prior
function* per member (Osband, Aslanides and Cassirer 2018): a fixed random network whose
output, times beta, is added to the member's mean head, so that members agree where data
constrain them and keep their priors' differences where none do. beta 0 is the plain
ensemble. Prints each one's disagreement AUROC and how many of its imagined transitions are
right.

    .venv/bin/python scripts/novelty_check.py runs/study23/s93/hard-{10..19} --priors 0,0.3,1,3
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.stats import rankdata

from imagine.envs.gesture_puzzle.evaluation import auroc, imagined_transitions
from imagine.envs.gesture_puzzle.rules import N_ACTIONS, N_MACROSTATES, macrostate_index
from imagine.learning.agent import load_agent
from imagine.learning.gate import support_distance
from imagine.models.world_model import PopulationWorldModel, WorldModel

sys.path.insert(0, str(Path(__file__).parent))
from m_offline import real_memory
from uncertainty_check import cycled, lookup_distance, nearest_start

BINS = ((0, 0), (1, 1), (2, 3), (4, 9), (10, None))


def visits(agent, z: torch.Tensor, action: torch.Tensor) -> np.ndarray:
    """Per transition, the number of M_R's real transitions from the same macrostate (V's
    classifier) with the same action."""
    held_mu, held_action = agent.memory_starts
    pairs = macrostate_index(agent.encoder.classify(held_mu).numpy()) * N_ACTIONS
    counts = np.bincount(pairs + held_action.numpy(), minlength=N_MACROSTATES * N_ACTIONS)
    return counts[macrostate_index(agent.encoder.classify(z).numpy()) * N_ACTIONS + action.numpy()]


@torch.no_grad()
def fit_error(agent, r: dict[str, torch.Tensor], memory_mu: torch.Tensor,
              memory_action: torch.Tensor, memory_next: torch.Tensor) -> np.ndarray:  # fmt: skip
    """Per imagined transition, M's error ||M(mu_j, a) - next_mu_j|| on the real transition j
    with the same action whose start mu_j is nearest z."""
    j = nearest_start(r, memory_mu, memory_action)
    model = agent.model.eval()
    predicted = model.most_likely(memory_mu[j], memory_action[j])
    return (predicted - memory_next[j]).norm(dim=-1).numpy()


@torch.no_grad()
def jitter(agent, r: dict[str, torch.Tensor], memory_mu: torch.Tensor, fraction: float,
           draws: int = 8, seed: int = 0) -> np.ndarray:  # fmt: skip
    """Per imagined transition (z, a), mean_n ||M(z + s * eps_n, a) - M(z, a)||, with s
    ``fraction`` times the per-dimension standard deviation of M_R's start mu."""
    model = agent.model.eval()
    generator = torch.Generator().manual_seed(seed)
    z, action = r["z"], r["action"]
    at = model.most_likely(z, action)
    s = fraction * memory_mu.std(0)
    moved = [model.most_likely(z + s * torch.randn(z.shape, generator=generator), action)
             for _ in range(draws)]  # fmt: skip
    return torch.stack([(m - at).norm(dim=-1) for m in moved]).mean(0).numpy()


def half_least(scores: np.ndarray) -> np.ndarray:
    """The half of the transitions with the lowest scores (a gate that accepts half)."""
    return np.argsort(scores, kind="stable")[: len(scores) // 2]


def logistic_fit(x: np.ndarray, y: np.ndarray, l2: float = 1e-3, steps: int = 50) -> np.ndarray:
    """Weights (intercept last) of a logistic regression of y on x, by Newton's method on the
    L2-penalized log-likelihood."""
    x = np.column_stack([x, np.ones(len(x))])
    w = np.zeros(x.shape[1])
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-x @ w))
        grad = x.T @ (p - y) + l2 * w
        hessian = (x * (p * (1 - p))[:, None]).T @ x + l2 * np.eye(len(w))
        step = np.linalg.solve(hessian, grad)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return w


def stack_features(ranks: np.ndarray, products: bool) -> np.ndarray:
    """Features of the combiner: the signals' within-run ranks in [0, 1] (N, S), with their
    pairwise products if ``products``."""
    if not products:
        return ranks
    pairs = [ranks[:, i] * ranks[:, j] for i in range(ranks.shape[1])
             for j in range(i + 1, ranks.shape[1])]  # fmt: skip
    return np.column_stack([ranks, *pairs])


def stacked_aurocs(ranks: list[np.ndarray], wrong: list[np.ndarray], products: bool) -> np.ndarray:
    """Leave one run out: a logistic combiner fitted on the other runs, its AUROC on this one."""
    out = []
    for i in range(len(ranks)):
        rest = [j for j in range(len(ranks)) if j != i]
        w = logistic_fit(np.concatenate([stack_features(ranks[j], products) for j in rest]),
                         np.concatenate([wrong[j] for j in rest]).astype(float))  # fmt: skip
        out.append(auroc(stack_features(ranks[i], products) @ w[:-1], wrong[i]))
    return np.array(out)


def oracle_bound(seen: np.ndarray, wrong: np.ndarray) -> float:
    """The best AUROC without any order among the never-visited: wrong visited ones first
    (2), the never-visited next (1, ties), right visited ones last (0)."""
    return auroc(np.where(seen == 0, 1.0, 2.0 * wrong), wrong)


class RandomPrior(torch.nn.Module):
    """One fixed random network per stacked MDN row, g_k(z, a) = W2 tanh(W1 [z, a] + b1),
    its output (D) added times beta to each of the row's components' means."""

    def __init__(self, rows: int, inputs: int, latent_dim: int, components: int, beta: float,
                 hidden: int = 64, seed: int = 123) -> None:  # fmt: skip
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.register_buffer("w1", torch.randn(rows, inputs, hidden, generator=g) / inputs**0.5)
        self.register_buffer("b1", 0.5 * torch.randn(rows, 1, hidden, generator=g))
        self.register_buffer("w2", torch.randn(rows, hidden, latent_dim, generator=g) / hidden**0.5)
        self.beta, self.components = beta, components

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.beta * (torch.tanh(x @ self.w1 + self.b1) @ self.w2).repeat(
            1, 1, self.components
        )


class PriorWorldModel(PopulationWorldModel):
    """A one-agent population M whose members' means carry a :class:`RandomPrior` (mean
    head output + beta g_k(z, a), before the residual z is added)."""

    def __init__(self, model: WorldModel, beta: float, lr: float, reward_loss: str) -> None:
        super().__init__([model], lr, reward_loss)
        components = model.mdn.n_components
        self.prior = RandomPrior(self.ensemble, self.latent_dim + self.n_actions,
                                 self.latent_dim, components, beta)  # fmt: skip

    def _heads(self, z, action, generators=None):
        heads = super()._heads(z, action, generators)
        x = torch.cat([z, F.one_hot(action, self.n_actions).to(z)], dim=-1)
        return (heads[0], heads[1] + self.prior(x), *heads[2:])


def member_batches(
    memory, share: float, members: int, batch: int, generator: torch.Generator
) -> Callable[[], dict[str, torch.Tensor]]:
    """A sampler of K batches of B, one after the other (as :meth:`PopulationWorldModel.update`
    takes them), member k's drawn only from its own fixed random ``share`` of the memory's
    transitions (bagging: what member k never sees, it must guess)."""
    held = len(memory)
    owned = torch.rand(members, held, generator=generator) < share
    owned[torch.arange(members), torch.randint(held, (members,), generator=generator)] = True
    pools = [torch.nonzero(row).squeeze(-1) for row in owned]

    def sample() -> dict[str, torch.Tensor]:
        index = torch.cat([pool[torch.randint(len(pool), (batch,), generator=generator)]
                           for pool in pools])  # fmt: skip
        return {name: value[:1, index] for name, value in memory.data.items()}

    return sample


def fresh_ensemble(run: Path, agent, beta: float, seed: int = 0, share: float = 1.0
                   ) -> PriorWorldModel:  # fmt: skip
    """A new M of the agent's form, trained on its real memory as the agent trains its own:
    ``model_updates`` bootstrapped updates per real transition held; with ``share`` < 1 each
    member only on its own random share of the transitions (:func:`member_batches`)."""
    c = agent.config
    if c.model_scales != "dropout":  # the clean scale heads' loss bypasses _heads
        raise SystemExit(f"error: {run}: --priors needs model_scales dropout")
    memory = real_memory(run, agent.encoder.latent_dim)
    torch.manual_seed(seed)
    model = WorldModel(agent.encoder.latent_dim, N_ACTIONS, n_components=c.n_components,
                       dropout=c.dropout, reward_hidden=c.reward_hidden,
                       terminal_hidden=c.terminal_hidden, residual=c.model_residual,
                       reward_dropout=c.reward_dropout, ensemble=c.model_ensemble,
                       covariance=c.model_covariance)  # fmt: skip
    population = PriorWorldModel(model, beta, c.model_lr, c.reward_loss)
    generator = torch.Generator().manual_seed(seed)
    if share < 1:
        sample = member_batches(memory, share, c.model_ensemble, c.model_batch, generator)
    else:

        def sample() -> dict[str, torch.Tensor]:
            return memory.sample(c.model_batch * c.model_ensemble, [generator])

    for _ in range(len(memory) * c.model_updates):
        population.update(sample(), [generator], resample=c.model_latents == "sample")
    return population.eval()


def check(
    run: Path, starts: int, fraction: float
) -> tuple[dict[str, float], np.ndarray, np.ndarray, np.ndarray]:
    agent = load_agent(run)
    if agent.memory_starts is None or agent.config.model_ensemble < 2:
        raise SystemExit(f"error: {run} holds no M_R or no ensemble of M")
    r, _, right = imagined_transitions(agent, starts, torch.Generator().manual_seed(0))
    wrong = ~right
    seen = visits(agent, r["z"], r["action"])
    disagreement = r["disagreement"].numpy()
    support = support_distance(r["z"], r["action"], *agent.memory_starts).numpy()
    memory = real_memory(run, agent.encoder.latent_dim)
    held = memory.state_dict("real")  # M_R's filled part
    lookup = lookup_distance(r, held["real.mu"], held["real.action"], held["real.next_mu"])
    fit = fit_error(agent, r, held["real.mu"], held["real.action"], held["real.next_mu"])
    cycle = (r["next_z"] - cycled(agent.encoder, r["next_z"])).norm(dim=-1).numpy()
    moves = jitter(agent, r, held["real.mu"], fraction)
    signals = (("d", disagreement), ("s", support), ("l", lookup), ("f", fit), ("c", cycle),
               ("j", moves))  # fmt: skip
    ranks = {k: rankdata(v) for k, v in signals}
    unseen, few = seen == 0, (seen >= 1) & (seen <= 3)
    out = {
        "wrong": float(wrong.mean()),
        "disagreement": auroc(disagreement, wrong),
        "support": auroc(support, wrong),
        "lookup": auroc(lookup.numpy(), wrong),
        "disagreement + support (ranks)": auroc(ranks["d"] + ranks["s"], wrong),
        "support + lookup (ranks)": auroc(ranks["s"] + ranks["l"], wrong),
        "all three (ranks)": auroc(ranks["d"] + ranks["s"] + ranks["l"], wrong),
        "fit (M's error at the nearest real start)": auroc(fit, wrong),
        "cycle (V's decode-encode)": auroc(cycle, wrong),
        "all five (ranks)": auroc(sum(ranks[k] for k in "dslfc"), wrong),
        "jitter (M's move under start noise)": auroc(moves, wrong),
        "three + jitter (ranks)": auroc(ranks["d"] + ranks["s"] + ranks["l"] + ranks["j"], wrong),
        "support + fit (ranks)": auroc(ranks["s"] + ranks["f"], wrong),
        "right, the half least suspect by all three (not an AUROC)": float(
            right[half_least(ranks["d"] + ranks["s"] + ranks["l"])].mean()
        ),
        "visits (oracle)": auroc(-seen.astype(float), wrong),
        "oracle bound": oracle_bound(seen, wrong),
        "disagreement, never visited": auroc(disagreement[unseen], wrong[unseen]),
        "support, never visited": auroc(support[unseen], wrong[unseen]),
        "fit, visited 1-3 times": auroc(fit[few], wrong[few]),
        "jitter, never visited": auroc(moves[unseen], wrong[unseen]),
        "jitter, visited 1-3 times": auroc(moves[few], wrong[few]),
    }
    scaled = np.column_stack([ranks[k] / len(wrong) for k in ("d", "s", "l", "f", "c", "j")])
    return out, seen, wrong, scaled


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--starts", type=int, default=100, help="real start states per agent")
    parser.add_argument("--priors", default="", help="betas of fresh prior ensembles, e.g. 0,1")
    parser.add_argument("--shares", default="", help="data shares of fresh bagged ensembles")
    parser.add_argument("--stack", action="store_true", help="fitted weights, leave one run out")
    parser.add_argument(
        "--jitter", type=float, default=0.3, help="start noise of jitter, a fraction of mu's spread"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        fresh = [(float(b), 1.0) for b in args.priors.split(",") if b]
        fresh += [(0.0, float(p)) for p in args.shares.split(",") if p]
    except ValueError as error:
        parser.error(f"--priors and --shares take numbers separated by commas ({error})")
    if any(not 0.0 < share <= 1.0 for _, share in fresh):
        parser.error(f"--shares must lie in (0, 1], got {args.shares}")
    rows, seen_all, wrong_all, prior_rows, ranks_all = [], [], [], [], []
    for run in args.runs:
        out, seen, wrong, ranks = check(run, args.starts, args.jitter)
        rows.append(out)
        ranks_all.append(ranks)
        seen_all.append(seen)
        wrong_all.append(wrong)
        print(run, ", ".join(f"{k} {v:.3f}" for k, v in out.items()), flush=True)
        if fresh:
            agent = load_agent(run)
            found = []
            for beta, share in fresh:
                model = fresh_ensemble(run, agent, beta, share=share)
                generator = torch.Generator().manual_seed(0)
                r, _, right = imagined_transitions(agent, args.starts, generator, model)
                u = r["disagreement"].numpy()
                few = np.isin(visits(agent, r["z"], r["action"]), [1, 2, 3])
                found.append((auroc(u, ~right), float(right.mean()), auroc(u[few], ~right[few])))
                print(f"  prior beta {beta}, share {share}: disagreement AUROC {found[-1][0]:.3f}, "
                      f"imagined right {found[-1][1]:.3f}, AUROC visited 1-3 times "
                      f"{found[-1][2]:.3f}", flush=True)  # fmt: skip
            prior_rows.append(found)
    seen, wrong = np.concatenate(seen_all), np.concatenate(wrong_all)
    print("\n| visits of the (state, action) pair in M_R | share of imagined transitions | wrong |")
    print("| --- | --- | --- |")
    for low, high in BINS:
        inside = (seen >= low) & (seen <= (high if high is not None else math.inf))
        name = f"{low}" if low == high else (f"{low}-{high}" if high is not None else f">= {low}")
        print(f"| {name} | {inside.mean():.1%} | {wrong[inside].mean():.1%} |")
    print(f"\n| AUROC over {len(rows)} runs | mean (std) | min-max |\n| --- | --- | --- |")
    for key in rows[0]:
        x = np.array([row[key] for row in rows])
        print(f"| {key} | {np.nanmean(x):.3f} ({np.nanstd(x, ddof=1):.3f}) | "
              f"{np.nanmin(x):.3f}-{np.nanmax(x):.3f} |")  # fmt: skip
    if args.stack and len(rows) > 1:
        print("\n| combiner of the ranks, leave one run out | AUROC mean (std) | min-max |")
        print("| --- | --- | --- |")
        sets = (("three", [0, 1, 2]), ("five", [0, 1, 2, 3, 4]), ("three + jitter", [0, 1, 2, 5]),
                ("six", [0, 1, 2, 3, 4, 5]))  # fmt: skip
        combiners = [(n, s, p) for n, s in sets for p in (False, True)]
        for signals, columns, products in combiners:
            name = f"logistic{' with pairwise products' if products else ''}, {signals} signals"
            x = stacked_aurocs([r[:, columns] for r in ranks_all], wrong_all, products)
            print(f"| {name} | {x.mean():.3f} ({x.std(ddof=1):.3f}) | "
                  f"{x.min():.3f}-{x.max():.3f} |")  # fmt: skip
    if prior_rows:
        x = np.array(prior_rows)  # (runs, variants, 3)
        print("\n| fresh ensemble: prior beta, each member's share of M_R | disagreement AUROC | "
              "imagined right | AUROC, pairs visited 1-3 times |")  # fmt: skip
        print("| --- | --- | --- | --- |")
        for j, (beta, share) in enumerate(fresh):
            print(f"| {beta}, {share} | {x[:, j, 0].mean():.3f} ({x[:, j, 0].std(ddof=1):.3f}) | "
                  f"{x[:, j, 1].mean():.1%} | {np.nanmean(x[:, j, 2]):.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
