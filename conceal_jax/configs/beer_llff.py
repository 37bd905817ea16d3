"""The capture "beer" read through its LLFF poses (poses_bounds.npy, no points), as a capture shared in the LLFF
layout is read: beer.py's 1/4 resolution and CPU adjustments, starting at random in its cameras' frustums from as
many points as lego.py starts from (3D-GS's 100k otherwise).

  python -m conceal_jax.main --config=conceal_jax/configs/beer_llff.py --workdir=workdirs/bench/beer_llff/teacher

`make bench-start` times its first steps against lego's; `make bench-train BENCH_ARGS=--scenes=beer_llff` trains
its teacher, and `make bench-conceal BENCH_ARGS="--scenes=beer_llff --rows=recommended,in_scene --widths=16"`
conceals in it: a forward-facing capture, where near-key poses and decoys are scaled by the key's view depth.
"""
from conceal_jax.configs import beer, lego


def get_config():
  config = beer.get_config()
  config.data.format = "llff"
  config.init.num_random_points = lego.get_config().init.num_random_points
  return config
