"""imagine."""
