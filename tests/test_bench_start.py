"""bench-start's arithmetic: step times per log window and the per-pixel ratio against lego."""
import pytest

from conceal_jax.configs import lego
from experiments import bench_start


def test_window_times_divide_each_window_by_its_steps():
  history = [dict(step=10, elapsed_s=5.0, num_pairs=100), dict(step=20, elapsed_s=6.0, num_pairs=80),
             dict(step=20, test_psnr=20.0), dict(step=40, elapsed_s=10.0, num_pairs=60)]
  assert bench_start.window_times(history) == [(10, 0.5, 100), (20, 0.1, 80), (40, 0.2, 60)]


def test_the_ratio_is_per_pixel_against_lego_of_as_many_steps():
  rows = [dict(scene="lego", steps=1000, step_us_per_pixel=4.0),
          dict(scene="beer_llff", steps=1000, step_us_per_pixel=9.0),
          dict(scene="beer_llff", steps=300, step_us_per_pixel=5.0, ratio_per_pixel=1.0, target_met=True)]
  lego, beer, beer_short = bench_start.with_ratios(rows)
  assert "ratio_per_pixel" not in lego
  assert beer["ratio_per_pixel"] == pytest.approx(2.25) and beer["target_met"] is False
  assert "ratio_per_pixel" not in beer_short and "target_met" not in beer_short  # no lego row of 300 steps


def test_beer_is_read_through_its_llff_poses_with_the_steps_asked():
  config = bench_start.scene_config("beer_llff", 300)
  assert config.data.format == "llff" and config.train.iterations == 300
  assert config.init.num_random_points == lego.get_config().init.num_random_points
  assert bench_start.scene_config("lego", 300).data.format == "auto"
