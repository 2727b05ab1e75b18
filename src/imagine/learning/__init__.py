"""Algorithm 1: memories, imagination, the population in lockstep, training, the agent."""
