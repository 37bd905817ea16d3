"""The real hand-held capture "beer" (COLMAP, 720x1280) at 1/4 resolution, as `make bench-train` trains it.

  python -m conceal_jax.main --config=conceal_jax/configs/beer.py --workdir=workdirs/bench/beer/teacher

The CPU adjustments of cpu_budget.py, with at most 40k Gaussians, and no opacity reset: the reset at 3k
pruned half of the Gaussians within 100 steps, and the 2k steps of densification left before step 5000 did
not rebuild them (the test PSNR it cost: experiments/results/train_configs.md). Test PSNR every 500 steps on
all 9 held-out views.
"""
from conceal_jax.configs import colmap, cpu_budget


def get_config():
  config = colmap.get_config()
  config.data.path = "../shared/data/colmap/beer"
  config.data.downscale = 4.0
  config = cpu_budget.apply(config, max_gaussians=40_000, eval_views=9)
  config.train.densify.opacity_reset_every = 10_000  # after densify.until: never
  return config
