"""Layer 0, below everything: atomic file writes, checkpoints, and the pieces every job shares."""
