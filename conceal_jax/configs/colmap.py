"""A real COLMAP capture: SfM initialisation, every 8th image held out, black background.

  python -m conceal_jax.main --config=conceal_jax/configs/colmap.py \
      --config.data.path=../shared/data/colmap/beer --workdir=workdirs/beer/teacher
"""
from conceal_jax.configs import default


def get_config():
  config = default.get_config()
  config.mode = "train"
  config.data.path = "../shared/data/colmap/beer"
  config.data.downscale = 4.0
  config.data.background = "black"
  config.init.kind = "points"
  config.train.iterations = 10_000
  return config
