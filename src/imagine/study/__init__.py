"""The paper's experiments and ours: sweeps, the reproduction, reports, comparisons."""
