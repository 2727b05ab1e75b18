"""V, M and C: the networks (paper section IV) and what feeds them."""
