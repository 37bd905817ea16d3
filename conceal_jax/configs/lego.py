"""NeRF-Synthetic lego at the paper's 200x200, as `make bench-train` trains it (and bench-conceal conceals in it).

The shared copy is stored at 400x400, so downscale 2 gives 1/4 of the original 800x800. The start is
sparser than the recipe's 100k random points to keep the first steps cheap on a CPU (densification grows
the count where needed).

  python -m conceal_jax.main --config=conceal_jax/configs/lego.py --workdir=workdirs/bench/lego/teacher
"""
from conceal_jax.configs import nerf_synthetic


def get_config():
  config = nerf_synthetic.get_config()
  config.data.path = "../shared/data/nerf_synthetic/lego"
  config.data.downscale = 2.0
  config.init.num_random_points = 5000
  return config
