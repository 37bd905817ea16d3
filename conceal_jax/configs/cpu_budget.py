"""The CPU adjustments the benchmark configs (lego.py, beer.py) make to the 3D-GS recipe: 10k steps in
well under an hour on 2 cores. Each one is a plain config option, so a GPU run can undo it; what each was
measured to save is in experiments/results/train_configs.md.

- train.densify.max_gaussians: a step costs about linearly in the Gaussian count, and an uncapped lego run
  passes 45k Gaussians by step 2000 and keeps growing; densification beyond the cap drops its weakest
  candidates;
- train.densify.until = 5000, half of the 10k run (3D-GS densifies over the first 15k of its 30k steps),
  so the only opacity reset is at 3k and the last 5k steps refine a fixed set of Gaussians;
- 4-pixel tiles with 64-pair segments: at these resolutions the splats are small, and the exact compositor
  then evaluates far fewer pixel-pairs than with 8-pixel tiles;
- a test PSNR every 500 steps on `eval_views` fixed test views, for train.json's PSNR-versus-time curve.
"""


def apply(config, max_gaussians: int, eval_views: int):
  config.train.densify.max_gaussians = max_gaussians
  config.train.densify.until = 5000
  config.render.tile_size = 4
  config.render.segment_size = 64
  config.train.eval_every = 500
  config.train.eval_views = eval_views
  return config
