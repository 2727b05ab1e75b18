"""C's belief: V's reading of the image, filtered through M's prediction of it (issue 14).

The paper's C acts on z_t, V's latent of the current image. V's latent of an image moves with
what does not matter to the task (which fragment, the lighting, the jitter) about as far as it
moves between neighbouring macrostates, while M, trained on the images' means, predicts the
next state's mean. An augmented agent can average the two, a filter of constant gain w:

    b_0 = mu_0,    b_t = w m_t + (1 - w) mu_t,

with m_t the mean of the component of M's mixture for (b_{t-1}, a_{t-1}) that best explains
mu_t (the highest posterior responsibility, :func:`~imagine.models.world_model.
responsible_mean`; member 0 of an ensemble). Where M knows one outcome that is its most likely
next state; where it knows several (a human whose hand may move), the one the image shows,
so the filter does not pull the belief towards an outcome that did not happen. w = 0 is the
paper's C. The baseline has no M and always acts on mu_t.
:class:`BeliefTracker` keeps b and the last action per row of a batch of episodes.
"""

from __future__ import annotations

import torch

from imagine.models.world_model import WorldModel


def fuse(prediction: torch.Tensor, mu: torch.Tensor, weight: float) -> torch.Tensor:
    """w m + (1 - w) mu: M's prediction and V's observation of the same step, averaged."""
    return weight * prediction + (1.0 - weight) * mu


class BeliefTracker:
    """The beliefs of ``n`` episodes run side by side by one agent (single-agent M).

    :meth:`observe` takes V's means of some rows' new observations and returns the states C
    should act on; :meth:`acted` records the actions taken; :meth:`restart` marks rows whose
    next observation starts an episode. With ``weight`` 0 or no ``model`` it returns mu.
    The beliefs live on M's device (V's means may come from another: V on a GPU, M on the CPU)."""

    def __init__(self, model: WorldModel | None, weight: float, n: int, latent_dim: int):
        self.model = model if weight > 0 else None
        self.weight = weight
        device = next(model.parameters()).device if model is not None else None
        self.belief = torch.zeros(n, latent_dim, device=device)
        self.action = torch.zeros(n, dtype=torch.long, device=device)
        self.started = torch.zeros(n, dtype=torch.bool, device=device)

    @torch.no_grad()
    def observe(self, mu: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """The beliefs (len(rows), D) of ``rows`` after their new observations' means ``mu``,
        on M's device."""
        if self.model is None:
            return mu
        device = self.belief.device
        rows = torch.as_tensor(rows, dtype=torch.long, device=device)
        belief = mu.to(device).clone()
        going = self.started[rows]
        if going.any():
            past = rows[going]
            mdn = self.model.members[0]
            was_training = mdn.training
            mdn.eval()  # M's most likely next state, without dropout
            m = mdn.explain(self.belief[past], self.action[past], belief[going])
            mdn.train(was_training)
            belief[going] = fuse(m, belief[going], self.weight)
        self.belief[rows] = belief
        self.started[rows] = True
        return belief

    def acted(self, actions: torch.Tensor, rows: torch.Tensor) -> None:
        device = self.action.device
        rows = torch.as_tensor(rows, dtype=torch.long, device=device)
        self.action[rows] = torch.as_tensor(actions, device=device)

    def restart(self, rows: torch.Tensor) -> None:
        self.started[torch.as_tensor(rows, dtype=torch.long, device=self.started.device)] = False
