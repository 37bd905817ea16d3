"""Layer 3: 3D Gaussian Splatting optimisation and scoring: initialisation, the Inria recipe (optimizer,
densification, losses), training, metrics and evaluation. Imports `data`, `splat`, `core`."""
