"""Layer 4: ConcealGS and what builds on it: the U-Net decoder, gradient guidance, the hidden image, the
check-view key, the objective, concealment and reveal. Imports every layer below."""
