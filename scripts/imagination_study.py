"""The discriminating experiments of issue 14: why imagination does not pay with V, and what does.

Each setting is one (method, agent-config overrides) pair on the `fast` preset, trained for both
tasks with 5 seeds (one population per task and setting), evaluated with 1000 greedy test
episodes at each budget, M's accuracy read by V's latent classifier. Prints one Markdown table:
success per task and budget (mean (std) over seeds) and M's sampled next-state accuracy on the
non-terminal transitions at the last budget.

    .venv/bin/python scripts/imagination_study.py --vae runs/vae-fast --out runs/study14 \\
        [--settings baseline,sample,mu,...] [--seeds 5] [--budgets 1000,2000] [--workers 2]

``--vae oracle`` runs the same settings on the true state (the oracle encoder): not a result
for the method with V, a diagnosis of what V costs.

Finished runs are read back; a stopped study resumes (it is `imagine reproduce`'s job machinery).
``--record DIR`` copies every run's evaluation and imagined-accuracy files (a few hundred bytes
each) into DIR with the same layout, so that ``--out DIR --table-only`` prints the same tables
after the run folders (agents, replay, gigabytes) are gone: the per-seed numbers a later study
is compared against, kept in the repository under ``studies/``.
Every setting spells out the fields it tests on the former `fast` imagination (FORMER_FAST), so it
means the same whatever the preset's defaults.
"""

from __future__ import annotations

import argparse
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from imagine.study.experiments import Job, LocalRunner, load_evaluations

PAPER_READING = {"model_latents": "sample", "imagination_draw": "sample",
                 "imagination_start": 1000}  # fmt: skip
HANDICAP = {"imagination_draw": "mode", "model_updates": 1, "model_batch": 32,
            "imagination_start": 100}  # fmt: skip
TRUST = {"model_ensemble": 5, "imagination_gate": "mask", "imagination_adaptive": True}
CLOUD = {"model_cloud_head": 128, "model_latents": "mu"}  # M's cloud head on V's means (round 26)
SUPPORT_TRUST = {"model_ensemble": 1, "imagination_gate": "mask",
                 "imagination_uncertainty": "support", "imagination_adaptive": True}  # fmt: skip
FORMER_FAST = {"imagination_start": 1000, "imagination_from": "current", "reward_updates": 0,
               "reward_loss": "logcosh", "model_residual": False, "dropout": 0.0,
               "reward_dropout": None, "belief": "observation", "value_expansion": 0,
               "n_imaginary_updates": 1, "terminal_hidden": 256,
               "target_update_period": 0, "model_ensemble": 1,
               "imagination_gate": "none"}  # fmt: skip
"""The `fast` preset's imagination before round 6 made Dyna's its default (and round 7 the
squared error for r and a residual M with 20% dropout, round 11 the belief and value expansion,
round 14 N_I = 2, round 18 a target network every 100 C updates, round 19 an ensemble of five
Ms behind the mask gate): every setting starts from it, so a setting means what it meant when
it ran."""
DYNA_100 = {"imagination_start": 100, "imagination_from": "memory"}
ROUND_6 = {**DYNA_100, "imagination_draw": "mode", "reward_updates": 6}
"""s39: the `fast` preset's imagination after round 6."""
RESIDUAL_20 = {"model_residual": True, "dropout": 0.2}
"""Round 7's M: the change of state, 20% dropout."""
TODAY = {**ROUND_6, **RESIDUAL_20, "belief": "filtered", "value_expansion": 2}
"""s59, the `fast` preset's augmented agent since round 11."""
SETTINGS: dict[str, tuple[str, dict[str, Any]]] = {
    # name: (method, overrides of the fast preset)
    "baseline": ("baseline", {}),
    "baseline, 2 real C updates per step": ("baseline", {"n_real_updates": 2}),
    "baseline, C on sampled inputs": ("baseline", {"controller_input": "sample"}),
    "augmented (paper: M on samples of N(mu, sigma), sampled imagination)": (
        "augmented",
        PAPER_READING,
    ),
    "augmented, C on sampled inputs": (
        "augmented",
        {**PAPER_READING, "controller_input": "sample"},
    ),
    "augmented, imagined next state = M's mode": (
        "augmented",
        {**PAPER_READING, "imagination_draw": "mode"},
    ),
    "augmented, M x4 updates (8 x 128 per step)": (
        "augmented",
        {**PAPER_READING, "model_updates": 8},
    ),
    "augmented, M on V's means (mu)": ("augmented", {**PAPER_READING, "model_latents": "mu"}),
    "augmented, M on mu, I_start 250": (
        "augmented",
        {**PAPER_READING, "model_latents": "mu", "imagination_start": 250},
    ),
    "augmented, M on mu, epsilon 0.2 in imagination": (
        "augmented",
        {**PAPER_READING, "model_latents": "mu", "imagination_epsilon": 0.2},
    ),
    "augmented, M on mu, change of state, mode, epsilon 0.2 in imagination": (
        "augmented",
        {
            **PAPER_READING,
            "model_latents": "mu",
            "model_residual": True,
            "imagination_draw": "mode",
            "imagination_epsilon": 0.2,
        },
    ),
    "augmented, change of state, imagined next state = M's mode": (
        "augmented",
        {**PAPER_READING, "model_residual": True, "imagination_draw": "mode"},
    ),
    "augmented, M on mu, imagined next state = M's mode": (
        "augmented",
        {**PAPER_READING, "model_latents": "mu", "imagination_draw": "mode"},
    ),
    "baseline, a real C update in place of each imagined one from I_start": (
        "baseline",
        {"imagination_start": 1000, "real_in_place_of_imagined": True},
    ),
    "augmented, mode, rollouts from states of M_R (Dyna)": (
        "augmented",
        {**PAPER_READING, "imagination_draw": "mode", "imagination_from": "memory"},
    ),
    "augmented, mode, rollouts from states of M_R, epsilon 0.2 in imagination": (
        "augmented",
        {
            **PAPER_READING,
            "imagination_draw": "mode",
            "imagination_from": "memory",
            "imagination_epsilon": 0.2,
        },
    ),
    "augmented, mode, N_I = 3 imagined C updates per step": (
        "augmented",
        {**PAPER_READING, "imagination_draw": "mode", "n_imaginary_updates": 3},
    ),
    "baseline, 3 real C updates in place of the 3 imagined ones from I_start": (
        "baseline",
        {"imagination_start": 1000, "real_in_place_of_imagined": True, "n_imaginary_updates": 3},
    ),
    # issue 15, model trust: the fast preset's augmented method (M's mode) with M handicapped
    "augmented, M handicapped (1 x 32 updates per step, I_start 100)": ("augmented", HANDICAP),
    "augmented, M handicapped, K = 5, mask gate, adaptive N_I": (
        "augmented",
        {**HANDICAP, **TRUST},
    ),
    "augmented, M handicapped, K = 5, random mask of the gate's rate, adaptive N_I": (
        "augmented",
        {**HANDICAP, **TRUST, "imagination_gate": "random"},
    ),
    # round 3: the space C and M read (V's active dimensions, standardized)
    "baseline, standardized latent": ("baseline", {"latent_space": "standardized"}),
    # issue 15: the fast preset's M, imagination from episode 100 as soon as trust allows
    "augmented, mode, I_start 100, K = 5, mask gate, adaptive N_I": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, **TRUST},
    ),
    "baseline, a real C update in place of each imagined one from episode 100": (
        "baseline",
        {"imagination_start": 100, "real_in_place_of_imagined": True},
    ),
    "augmented, mode, I_start 100, no trust (one M, every imagined update made)": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100},
    ),
    "augmented, mode, I_start 100, one M, mask gate on support, adaptive N_I": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, **SUPPORT_TRUST},
    ),
    "diagnosis: augmented, I_start 100, a perfect M (the rules through V)": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, "imagination_model": "true"},
    ),
    "diagnosis: as s26, rollouts from states of M_R (Dyna)": (
        "augmented",
        {
            "imagination_draw": "mode",
            "imagination_start": 100,
            "imagination_model": "true",
            "imagination_from": "memory",
        },
    ),
    "augmented, mode, I_start 100, rollouts from states of M_R (Dyna)": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, "imagination_from": "memory"},
    ),
    "augmented, mode, I_start 100, N_I = 3": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, "n_imaginary_updates": 3},
    ),
    "augmented, mode, I_start 100, M x4 updates (8 x 128 per step)": (
        "augmented",
        {"imagination_draw": "mode", "imagination_start": 100, "model_updates": 8},
    ),
    # round 6: what separates a perfect M's Dyna (s27) from the learned M's (s28)
    "diagnosis: as s27, the next macrostate's mean latent (a perfect M's mode, no fresh image)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "imagination_model": "true_mean"},
    ),
    "augmented, I_start 100, Dyna, a draw from M's heaviest component": (
        "augmented",
        {**DYNA_100, "imagination_draw": "component"},
    ),
    "augmented, I_start 100, Dyna, M on mu, a draw from M's heaviest component": (
        "augmented",
        {**DYNA_100, "imagination_draw": "component", "model_latents": "mu"},
    ),
    "augmented, I_start 100, Dyna, M on mu, mode": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "model_latents": "mu"},
    ),
    "augmented, I_start 100, Dyna, mode, imagined updates only while M is trusted": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "imagination_adaptive": True},
    ),
    "diagnosis: as s28, the rules' reward and end (the learned M's next state)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "imagination_model": "true_reward"},
    ),
    "diagnosis: as s31, the learned reward and end (the rules' next state, mean latent)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "imagination_model": "true_state"},
    ),
    "diagnosis: as s28, the rules' end (the learned M's next state and reward)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "imagination_model": "true_end"},
    ),
    "augmented, I_start 100, Dyna, mode, r and d 8 updates per step (6 alone)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "reward_updates": 6},
    ),
    "augmented, I_start 100, Dyna, mode, r and d 16 updates per step (14 alone)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "reward_updates": 14},
    ),
    "augmented, as s39 (the fast preset), r's loss the squared error": (
        "augmented",
        {**ROUND_6, "reward_loss": "mse"},
    ),
    "augmented, I_start 100, Dyna, mode, r's loss the squared error (r and d 2 updates)": (
        "augmented",
        {**DYNA_100, "imagination_draw": "mode", "reward_loss": "mse"},
    ),
    "augmented, as s41, a residual M with 20% dropout": (
        "augmented",
        {**ROUND_6, "reward_loss": "mse", **RESIDUAL_20},
    ),
    "augmented, as s39, a residual M with 20% dropout": ("augmented", {**ROUND_6, **RESIDUAL_20}),
    "augmented, as s41, a residual M with 20% dropout in the MDN (none in r and d)": (
        "augmented",
        {**ROUND_6, "reward_loss": "mse", **RESIDUAL_20, "reward_dropout": 0.0},
    ),
    # round 8: from the fast preset (s44) towards a perfect M's 96.3 on hard (s27)
    "augmented, as s44 (the fast preset), N_I = 2 imagined C updates per step": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "n_imaginary_updates": 2},
    ),
    "augmented, as s44 (the fast preset), no dropout in r and d": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "reward_dropout": 0.0},
    ),
    # round 9: a tempered draw instead of the mode (M's sampled accuracy at the agent's draw)
    "augmented, as s44, imagined next state a draw at temperature 0.5": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "imagination_draw": "sample", "imagination_temperature": 0.5},
    ),
    "augmented, as s44, imagined next state a draw at temperature 0.25 (scales x 0.5)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "imagination_draw": "sample", "imagination_temperature": 0.25},
    ),
    # value expansion (issue 16): M in C's targets, beside or instead of imagined transitions
    "augmented, as s44, C's targets expanded 2 steps through M": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "value_expansion": 2},
    ),
    "augmented, as s44, C's targets expanded 2 steps through M, no imagined transitions": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "value_expansion": 2, "n_imaginary_updates": 0},
    ),
    # a stochastic human (issue 16): the hand moves with probability 0.3 after each action
    "baseline, a stochastic human (hand_switch_prob 0.3)": (
        "baseline",
        {"hand_switch_prob": 0.3},
    ),
    "augmented, as s44, a stochastic human (hand_switch_prob 0.3)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "hand_switch_prob": 0.3},
    ),
    "augmented, as s44, a stochastic human (0.3), a one-component M (the control)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "hand_switch_prob": 0.3, "n_components": 1},
    ),
    # value expansion weighted in the style of STEVE (issue 16): an ensemble of 5 M
    "augmented, as s50, 5 members of M, the horizons weighted as STEVE does": (
        "augmented",
        {
            **ROUND_6,
            **RESIDUAL_20,
            "value_expansion": 2,
            "model_ensemble": 5,
            "value_expansion_weighting": "steve",
        },
    ),
    "augmented, as s50, 5 members of M (the control for s55: plain MVE through member 0)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "value_expansion": 2, "model_ensemble": 5},
    ),
    # round 11: C acts on V's observation filtered through M's prediction of it
    "augmented, as s44, C acts on a belief through M's mode, in training too (run at 7bc2e51)": (
        "augmented",
        {
            **ROUND_6,
            **RESIDUAL_20,
            "belief": "filtered",
            "belief_weight": 0.5,
            "belief_in_training": True,
        },
    ),
    "augmented, as s44, the trained C acts on the belief (w = 0.5; the fast preset)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "belief": "filtered", "belief_weight": 0.5},
    ),
    "augmented, as s58, C's targets expanded 2 steps through M (s50 acting on the belief)": (
        "augmented",
        {**ROUND_6, **RESIDUAL_20, "belief": "filtered", "value_expansion": 2},
    ),
    # issue 15 on round 11's fast agent (s59): M handicapped, with and without trust
    "augmented, as s59 (the fast preset), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**TODAY, **HANDICAP},
    ),
    "augmented, as s60, K = 5, mask gate, adaptive N_I, STEVE's weighting of the expansion": (
        "augmented",
        {**TODAY, **HANDICAP, **TRUST, "value_expansion_weighting": "steve"},
    ),
    "augmented, as s61, a random mask of the gate's rate": (
        "augmented",
        {**TODAY, **HANDICAP, **TRUST, "value_expansion_weighting": "steve"}
        | {"imagination_gate": "random"},
    ),
    "augmented, as s60, one M, mask gate on support, adaptive N_I": (
        "augmented",
        {**TODAY, **HANDICAP, **SUPPORT_TRUST},
    ),
    # issue 14: M's draws with a full covariance (V's dimensions move together)
    "augmented, as s59 (the fast preset), M's components with a full covariance": (
        "augmented",
        {**TODAY, "model_covariance": "full"},
    ),
    "augmented, as s64, M on V's means": (
        "augmented",
        {**TODAY, "model_covariance": "full", "model_latents": "mu"},
    ),
    "augmented, as s65, no dropout in the MDN (r and d keep 20%)": (
        "augmented",
        {
            **TODAY,
            "model_covariance": "full",
            "model_latents": "mu",
            "dropout": 0.0,
            "reward_dropout": 0.2,
        },
    ),
    # issue 14, round 13: the scales of M's predictions fitted on the network without dropout
    "augmented, as s64, the scales fitted without dropout's masks": (
        "augmented",
        {**TODAY, "model_covariance": "full", "model_scales": "clean"},
    ),
    "augmented, as s65, the scales fitted without dropout's masks": (
        "augmented",
        {**TODAY, "model_covariance": "full", "model_latents": "mu", "model_scales": "clean"},
    ),
    # issue 14, round 14: C learns more from imagination per step, early where the fine curves
    # ask it to pay (round 8 measured N_I = 2 on s44, before the belief and value expansion)
    "augmented, as s59 (the fast preset), N_I = 2 imagined C updates per step": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 2},
    ),
    "augmented, as s59 (the fast preset of rounds 14-17), N_I = 3 imagined C updates per step": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 3},
    ),
    "baseline, 2 real C updates in place of s69's 2 imagined ones from episode 100": (
        "baseline",
        {"imagination_start": 100, "real_in_place_of_imagined": True, "n_imaginary_updates": 2},
    ),
    "augmented, as s69 (the fast preset), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**TODAY, **HANDICAP, "n_imaginary_updates": 2},
    ),
    "augmented, as s70 (N_I = 3), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**TODAY, **HANDICAP, "n_imaginary_updates": 3},
    ),
    "baseline, 3 real C updates in place of s70's 3 imagined ones from episode 100": (
        "baseline",
        {"imagination_start": 100, "real_in_place_of_imagined": True, "n_imaginary_updates": 3},
    ),
    # the control inside the augmented agent: M's belief and value expansion kept, imagination's
    # C updates replaced by as many on real batches (from the first step, N_R = 4)
    "augmented, as s70, 3 real C updates in place of the 3 imagined ones": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 0, "n_real_updates": 4},
    ),
    "augmented, as s75 (N_R = 4) with s70's 3 imagined C updates as well": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 3, "n_real_updates": 4},
    ),
    # issue 14, round 15: what replay cannot give, the actions C's behaviour did not take
    "augmented, as s70, imagination over every action (one step each)": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 3, "imagination_actions": "all"},
    ),
    "augmented, as s77 (every action), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**TODAY, **HANDICAP, "n_imaginary_updates": 3, "imagination_actions": "all"},
    ),
    # round 15: C's values diverged in one seed of s75 and of s77 (no target network, the
    # paper's C, with four updates a step); a target network copied every 500 C updates
    "augmented, as s77 (every action), C with a target network (copied every 500 updates)": (
        "augmented",
        {
            **TODAY,
            "n_imaginary_updates": 3,
            "imagination_actions": "all",
            "target_update_period": 500,
        },
    ),
    "baseline, C with a target network (copied every 500 updates)": (
        "baseline",
        {"target_update_period": 500},
    ),
    # issue 14 round 16 / issue 15: s77's every-action backups are 92-96% right, and its wrong
    # ones are where (z, a) is far from every real start with action a (support AUROC
    # 0.77-0.82 on s77 at 2000 episodes); keep only the supported ones (mask gate, one M)
    "augmented, as s77 (every action), a mask gate on support (one M)": (
        "augmented",
        {
            **TODAY,
            "n_imaginary_updates": 3,
            "imagination_actions": "all",
            "imagination_gate": "mask",
            "imagination_uncertainty": "support",
        },
    ),
    "augmented, as s81, a random mask of the gate's rate (the control)": (
        "augmented",
        {
            **TODAY,
            "n_imaginary_updates": 3,
            "imagination_actions": "all",
            "imagination_gate": "random",
            "imagination_uncertainty": "support",
        },
    ),
    # round 16: imagination from episode 10 instead of 100, for the 250-500 cells where s70 is
    # level with the baseline, with the adaptive ratio's trust check: no imagined C update
    # while M's one-step modes on the newest real transitions are right less than 80%
    "augmented, as s70, imagining from episode 10, adaptive N_I": (
        "augmented",
        {
            **TODAY,
            "n_imaginary_updates": 3,
            "imagination_start": 10,
            "imagination_adaptive": True,
        },
    ),
}
S84 = {**TODAY, "n_imaginary_updates": 3, "imagination_actions": "all",
       "imagination_gate": "mask", "imagination_uncertainty": "support",
       "imagination_actions_until": 1000}  # fmt: skip
"""s84: s81's gated every-action backups until episode 1000, then s70's imagination."""
S86 = {**TODAY, "n_imaginary_updates": 3, "target_update_period": 100}
"""s86, the `fast` preset's augmented agent since round 18."""
SETTINGS |= {
    # issue 15 / round 17: s81's gated every-action backups lead early (500-1000 episodes) and
    # fall behind s70 late; both, one after the other: s81 until episode 1000, then s70
    "augmented, as s81 until episode 1000, then as s70 (the paper's rollouts, ungated)": (
        "augmented",
        S84,
    ),
    # issue 18: the fast preset's d-network at 2 x 128 units instead of 2 x 256 (a third of a
    # step's time), against s70 on the same V
    "augmented, as s70, the d-network 2 x 128": (
        "augmented",
        {**TODAY, "n_imaginary_updates": 3, "terminal_hidden": 128},
    ),
}
SETTINGS |= {
    # round 17: on this session's V one seed of five of s70 and of s84 diverges (C has no target
    # network); a target network copied every 100 C updates (25 real steps) instead of s79's 500
    "augmented, as s70, C with a target network (copied every 100 updates): the fast preset": (
        "augmented",
        S86,
    ),
    "augmented, as s84, C with a target network (copied every 100 updates)": (
        "augmented",
        {**S84, "target_update_period": 100},
    ),
}
SETTINGS |= {
    # round 18: is the gain of s86 the target network's? The baseline with the same C (s80's
    # period 500 slowed the baseline; 100 is what s86 takes)
    "baseline, C with a target network (copied every 100 updates)": (
        "baseline",
        {"target_update_period": 100},
    ),
}
SETTINGS |= {
    # issue 15 on round 18's fast agent (s86): does a handicapped M hurt it, and does trust
    # (K = 5, the mask gate on the members' disagreement, the adaptive ratio) keep it level
    # with the baseline, where a random mask of the gate's rate does not?
    "augmented, as s86 (the fast preset), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**S86, **HANDICAP},
    ),
    "augmented, as s89, K = 5, mask gate on disagreement, adaptive N_I": (
        "augmented",
        {**S86, **HANDICAP, **TRUST},
    ),
    "augmented, as s90, a random mask of the gate's rate (the control)": (
        "augmented",
        {**S86, **HANDICAP, **TRUST, "imagination_gate": "random"},
    ),
    # issue 15's "it helps": the same trust on the fast agent's own M (not handicapped)
    "augmented, as s86 (the fast preset), K = 5, mask gate on disagreement, adaptive N_I": (
        "augmented",
        {**S86, **TRUST},
    ),
    # s92 is behind s86 on `original` early: the adaptive ratio's late start, or the ensemble?
    "augmented, as s92 without the adaptive ratio (imagined updates from episode 100)": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False},
    ),
    # issue 15's two gates: MACURA's stop (a rollout ends at its first u > tau) against s93's
    # M2AC mask (each u > tau dropped)
    "augmented, as s93 with the stop gate": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, "imagination_gate": "stop"},
    ),
    # does s93's gate matter, or only its ensemble? s93 without any gate, and s93 with a
    # random mask of the gate's rate (the control)
    "augmented, as s93 without the gate (K = 5 only)": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, "imagination_gate": "none"},
    ),
    "augmented, as s93 with a random mask of the gate's rate (the control)": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, "imagination_gate": "random"},
    ),
    # issue 15's "never hurts" with today's default trust (s93's: K = 5, the mask gate, no
    # adaptive ratio) on a handicapped M, and its random-mask control
    "augmented, as s93 (the fast preset), M handicapped (1 x 32 updates per step)": (
        "augmented",
        {**S86, **HANDICAP, **TRUST, "imagination_adaptive": False},
    ),
    "augmented, as s97, a random mask of the gate's rate (the control)": (
        "augmented",
        {**S86, **HANDICAP, **TRUST, "imagination_adaptive": False, "imagination_gate": "random"},
    ),
    # round 22: s93's value expansion follows member 0's modes; the members' mean mode is M's
    # better point prediction (round 21): do C's targets gain from it?
    "augmented, as s93 with value expansion through the members' mean mode": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, "value_expansion_members": "mean"},
    ),
    # round 26: M's mixture from a cloud head of its predicted point (model_cloud_head), on
    # V's means (offline its draws are right 79% against the plain M's 59-65%)
    "augmented, as s93 with M's cloud head, learning from V's means": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, **CLOUD},
    ),
    # s100's control: the plain MDN on V's means (is s100's difference the head's?)
    "augmented, as s93 learning from V's means": (
        "augmented",
        {**S86, **TRUST, "imagination_adaptive": False, "model_latents": "mu"},
    ),
}
SHORT = {name: f"s{i}" for i, name in enumerate(SETTINGS)}


def jobs_of(setting: str, out: Path, tasks: list[str], seeds: int, budgets: tuple[int, ...],
            vae: str) -> list[Job]:  # fmt: skip
    method, overrides = SETTINGS[setting]
    fields = tuple(sorted({**FORMER_FAST, **overrides}.items()))
    return [
        Job(
            str(out / SHORT[setting] / f"{task}-{seed}"),
            task,
            method,
            seed,
            budgets,
            encoder="oracle" if vae == "oracle" else "vae",
            vae_run=None if vae == "oracle" else vae,
            overrides=fields,
        )
        for task in tasks
        for seed in range(seeds)
    ]


def record(jobs: list[Job], out: Path, dest: Path) -> int:
    """Copy the jobs' ``evaluation-*.json`` and ``imagined-*.json`` from ``out`` into ``dest``
    at the same relative paths; returns how many files were copied."""
    copied = 0
    for job in jobs:
        folder = Path(job.folder)
        if not folder.is_dir():
            continue
        target = dest / folder.relative_to(out)
        for path in sorted([*folder.glob("evaluation-*.json"), *folder.glob("imagined-*.json")]):
            target.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target / path.name)
            copied += 1
    return copied


def cell(values: list[float]) -> str:
    if not values:
        return "-"
    x = 100 * np.array(values)
    std = f" ({x.std(ddof=1):.1f})" if len(x) > 1 else ""
    return f"{x.mean():.1f}{std}" + ("" if len(x) >= 5 else f" [n={len(x)}]")


def from_terminal(accuracy: dict[str, float], task: str) -> float:
    """M's most-likely accuracy on the transitions from terminal states (generalization), from
    the accuracies over all 192 x 6 transitions and over the non-terminal ones."""
    from imagine.envs.gesture_puzzle.rules import all_macrostates, is_terminal

    if "transition_terminal" in accuracy:
        return accuracy["transition_terminal"]
    total, terminal = 192 * 6, int(is_terminal(all_macrostates(), task).sum()) * 6
    right = accuracy["transition"] * total - accuracy["transition_nonterminal"] * (total - terminal)
    return right / terminal


def gate_cell(found: list[dict[str, float]]) -> str:
    """The share of each run's imagined transitions its gate keeps (for a run without a gate,
    what the mask gate would keep of them), and the share right among the kept and the
    dropped (runs that dropped none leave the latter out)."""
    if not found or "accepted" not in found[0]:
        return "-"
    kept = [x["state_accepted"] for x in found if not math.isnan(x["state_accepted"])]
    dropped = [x["state_rejected"] for x in found if not math.isnan(x["state_rejected"])]
    return f"{cell([x['accepted'] for x in found])} ({cell(kept)} / {cell(dropped)})"


def imagined(job: Job, budget: int) -> dict[str, float] | None:
    """The imagined-transition accuracy of a finished augmented run at its last checkpoint
    (cached in imagined-NNNNN.json)."""
    from imagine.checkpoint import read_json, write_json
    from imagine.envs.gesture_puzzle.evaluation import imagined_accuracy
    from imagine.learning.agent import load_agent

    path = Path(job.folder) / f"imagined-{budget:05d}.json"
    if path.is_file():
        return read_json(path, "imagined accuracy")
    if job.method != "augmented" or not job.evaluation_path(budget).is_file():
        return None
    if not (Path(job.folder) / "agent.json").is_file():  # a record (--record): no agent to ask
        return None
    agent = load_agent(job.folder)
    if agent.episode != budget:
        return None
    result = imagined_accuracy(agent)
    write_json(path, result)
    return result


def table(settings: list[str], out: Path, tasks: list[str], seeds: int,
          budgets: tuple[int, ...], vae: str) -> str:  # fmt: skip
    last = budgets[-1]
    head = [f"{t} {b}" for t in tasks for b in budgets] + [f"M sampled {t}" for t in tasks]
    head += [f"imagined right {t} (state / reward)" for t in tasks]
    head += [f"M from terminal states {t}" for t in tasks]
    head += [f"gate accepts {t} (imagined right: accepted / rejected)" for t in tasks]
    lines = ["| setting | " + " | ".join(head) + " |", "| --- " * (len(head) + 1) + "|"]
    for setting in settings:
        jobs = jobs_of(setting, out, tasks, seeds, budgets, vae)
        rows = load_evaluations(jobs)
        cells = [cell([r["success"] for r in rows if r["task"] == t and r["budget"] == b])
                 for t in tasks for b in budgets]  # fmt: skip
        for t in tasks:
            accs = [
                r["model_accuracy"]["transition_sampled"]
                for r in rows
                if r["task"] == t and r["budget"] == last and r["model_accuracy"]
            ]
            tempered = [
                r["model_accuracy"]["transition_sampled_tempered"]
                for r in rows
                if r["task"] == t and r["budget"] == last
                and "transition_sampled_tempered" in (r["model_accuracy"] or {})
            ]  # fmt: skip
            cells.append(
                cell(accs) + (f" (at its temperature {cell(tempered)})" if tempered else "")
            )
            variation = [
                r["hand_calibration"]["total_variation"]
                for r in rows
                if r["task"] == t and r["budget"] == last and "hand_calibration" in r
            ]
            if variation:  # a stochastic human: M's hand probabilities against the truth
                cells[-1] += f" (hand probabilities off by {cell(variation)}%, total variation)"
        found = {t: [x for x in (imagined(j, last) for j in jobs if j.task == t) if x]
                 for t in tasks}  # fmt: skip
        for t in tasks:
            both = [cell([x[k] for x in found[t]]) for k in ("state", "reward")]
            cells.append(" / ".join(both) if found[t] else "-")
        for t in tasks:
            general = [
                from_terminal(r["model_accuracy"], t)
                for r in rows
                if r["task"] == t and r["budget"] == last and r["model_accuracy"]
            ]
            cells.append(cell(general))
        cells += [gate_cell(found[t]) for t in tasks]
        lines.append(f"| {SHORT[setting]}: {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def iqm_table(settings: list[str], out: Path, tasks: list[str], seeds: int,
              budgets: tuple[int, ...], vae: str) -> str:  # fmt: skip
    """Success % per setting, task and budget as IQM [95% bootstrap interval] over the seeds."""
    from imagine.study.report import iqm_interval

    head = [f"{t} {b}" for t in tasks for b in budgets]
    lines = ["| setting (IQM [95% CI]) | " + " | ".join(head) + " |",
             "| --- " * (len(head) + 1) + "|"]  # fmt: skip
    for setting in settings:
        rows = load_evaluations(jobs_of(setting, out, tasks, seeds, budgets, vae))
        cells = []
        for t in tasks:
            for b in budgets:
                x = np.array(
                    [100 * r["success"] for r in rows if r["task"] == t and r["budget"] == b]
                )
                cells.append("{:.1f} [{:.1f}, {:.1f}]".format(*iqm_interval(x)) if len(x) else "-")
        lines.append(f"| {SHORT[setting]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def curves_table(settings: list[str], out: Path, tasks: list[str], seeds: int,
                 budgets: tuple[int, ...], vae: str) -> str:  # fmt: skip
    """Each setting's learning curve over the budgets (``imagine reproduce``'s curves table):
    the area under the success curve per seed (mean, IQM [95% bootstrap CI]) and the episodes
    to 90%."""
    from imagine.study.report import curve_summary, curve_table

    rows = []
    for setting in settings:
        jobs = jobs_of(setting, out, tasks, seeds, budgets, vae)
        rows += [{**r, "method": SHORT[setting]} for r in load_evaluations(jobs)]
    return curve_table(curve_summary(rows)).replace("| method |", "| setting |")


def compare_table(pair: list[str], out: Path, tasks: list[str], seeds: int,
                  budgets: tuple[int, ...], vae: str) -> str:  # fmt: skip
    """Two settings cell by cell (task, budget): mean success of each and Welch's t-test (and
    Mann-Whitney's U) p-value over their seeds, the test `make run`'s tables are held to
    when a lever must leave them unchanged in distribution (issue 18)."""
    from scipy.stats import mannwhitneyu, ttest_ind

    rows = [load_evaluations(jobs_of(s, out, tasks, seeds, budgets, vae)) for s in pair]
    a, b = (SHORT[s] for s in pair)
    lines = [f"| task | episodes | {a} | {b} | Welch p | Mann-Whitney p |",
             "| --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for t in tasks:
        for budget in budgets:
            x, y = (
                np.array(
                    [100 * r["success"] for r in got if r["task"] == t and r["budget"] == budget]
                )
                for got in rows
            )
            if not len(x) or not len(y):
                continue
            welch = ttest_ind(x, y, equal_var=False).pvalue if np.ptp(np.r_[x, y]) else 1.0
            mw = mannwhitneyu(x, y).pvalue
            means = " | ".join(f"{v.mean():.1f} ({v.std(ddof=1):.1f})" for v in (x, y))
            lines.append(f"| {t} | {budget} | {means} | {welch:.2f} | {mw:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--vae", required=True, help="V run folder, or 'oracle' for the true state (a diagnosis)"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/study14"))
    parser.add_argument(
        "--settings",
        default=",".join(SHORT.values()),
        help="setting numbers (s0,s1,...) in the order to run them",
    )
    parser.add_argument("--tasks", default="original,hard")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--budgets", default="1000,2000")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--table-only", action="store_true")
    parser.add_argument(
        "--compare", metavar="SA,SB", help="also test two settings cell by cell (Welch, U test)"
    )
    parser.add_argument(
        "--record", type=Path, metavar="DIR", help="copy the runs' result files into DIR"
    )
    args = parser.parse_args()
    by_short = {v: k for k, v in SHORT.items()}
    settings = [by_short[s] for s in args.settings.split(",")]
    tasks = args.tasks.split(",")
    budgets = tuple(int(b) for b in args.budgets.split(","))
    if not args.table_only:
        # task-major: every setting of the first task, then of the next
        jobs = [j for t in tasks for s in settings
                for j in jobs_of(s, args.out, [t], args.seeds, budgets, args.vae)]  # fmt: skip
        LocalRunner(args.workers).run(
            [j for j in jobs if not j.finished()],
            on_start=lambda job: None,
            on_done=lambda job, error: print(f"{job.folder}: {error or 'done'}", flush=True),
        )
    print(table(settings, args.out, tasks, args.seeds, budgets, args.vae))
    print()
    print(iqm_table(settings, args.out, tasks, args.seeds, budgets, args.vae))
    if len(budgets) > 2:  # a learning curve
        print()
        print(curves_table(settings, args.out, tasks, args.seeds, budgets, args.vae))
    if args.compare:
        print()
        pair = [by_short[s] for s in args.compare.split(",")]
        print(compare_table(pair, args.out, tasks, args.seeds, budgets, args.vae))
    if args.record:
        jobs = [j for s in settings
                for j in jobs_of(s, args.out, tasks, args.seeds, budgets, args.vae)]  # fmt: skip
        print(f"\n{record(jobs, args.out, args.record)} result files recorded in {args.record}")


if __name__ == "__main__":
    main()
