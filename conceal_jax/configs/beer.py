"""The real hand-held capture "beer" (COLMAP, 720x1280) at 1/4 resolution, as `make bench-train` trains it.

  python -m conceal_jax.main --config=conceal_jax/configs/beer.py --workdir=workdirs/bench/beer/teacher
"""
from conceal_jax.configs import colmap


def get_config():
  config = colmap.get_config()
  config.data.path = "../shared/data/colmap/beer"
  config.data.downscale = 4.0
  return config
