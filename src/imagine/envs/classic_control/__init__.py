"""Gymnasium's classic-control environments of the suite (CartPole-v1, Acrobot-v1): their true
dynamics as a perfect M, for imagination's diagnostics (issue 57)."""
