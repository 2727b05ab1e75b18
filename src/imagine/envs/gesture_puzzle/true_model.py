"""A perfect M in V's latent space: the environment's own rules, observed through V.

A diagnostic, never a result (as the oracle encoder is for V): with ``imagination_model:
true`` the agent imagines with this in place of its learned M. From an imagined state z it
reads the macrostate with V's latent classifier (which the agent itself never uses), applies
the action by the rules, draws a fresh image of the next macrostate (a new fragment per cube
and hand, as the environment does at every real step) and hands C that image's mu, with the
rules' reward and end. So an imagined transition is distributed as a real one would be, and
what imagination then does for C is the most any learned M could give it with this V and this
form of imagination (rollouts, their start, breadth and depth, C's policy inside them).
Whatever separates it from a real C update (``real_in_place_of_imagined``) is not M's fault.
With ``fresh=False`` (``imagination_model: true_mean``) it hands the mean latent of the next
macrostate's images instead (V's reference latents): a perfect M's *mode*, the same next
macrostate without the spread of its images.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from imagine.envs.gesture_puzzle.rules import apply_actions, is_terminal, macrostate_index, rewards
from imagine.envs.gesture_puzzle.scene import SceneComposer
from imagine.models.world_model import Prediction


class TrueLatentModel:
    """The rules as an M in population form (the calls :func:`imagine.learning.imagination.
    imagine_rollouts` makes): ``predict``, ``is_terminal`` and ``predict_reward`` on latents
    (P, B, D). ``seed`` seeds the fragments of the images it draws; ``fresh=False``: the next
    macrostate's mean latent (``encoder.state_latents()``) in place of a fresh image's."""

    def __init__(
        self, encoder, composer: SceneComposer, task: str, seed: int = 0, fresh: bool = True
    ) -> None:
        self.encoder, self.composer, self.task, self.fresh = encoder, composer, task, fresh
        self.rng = np.random.default_rng(seed)
        self.means = None if fresh else encoder.state_latents()

    def _states(self, z: torch.Tensor) -> np.ndarray:
        """The macrostates V's classifier reads from latents (..., D): (N, 4)."""
        return self.encoder.classify(z.reshape(-1, z.shape[-1])).numpy()

    @torch.no_grad()
    def predict(
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generators: Sequence[torch.Generator | None] = (),
        draw: str = "mode",
    ) -> Prediction:
        """The mu of a fresh image of the true next macrostate (or its mean latent); no
        disagreement."""
        nxt = apply_actions(self._states(z), action.reshape(-1).cpu().numpy())
        if self.means is not None:
            mu = self.means[torch.as_tensor(macrostate_index(nxt))]
        else:
            mu, _ = self.encoder.encode(self.composer.sample(self.rng, nxt), nxt)
        return Prediction(mu.to(z).view(z.shape), torch.zeros(z.shape[:-1], device=z.device))

    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        done = is_terminal(self._states(z), self.task)
        return torch.as_tensor(done, device=z.device).view(z.shape[:-1])

    def predict_reward(self, z: torch.Tensor) -> torch.Tensor:
        r = torch.as_tensor(rewards(self._states(z), self.task), dtype=torch.float32)
        return r.to(z.device).view(z.shape[:-1])
