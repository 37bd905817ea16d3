"""The README's figure, experiments/results/overview.png, from the images bench-conceal keeps under
experiments/results/revealed/: for the recommended recipe's run on each scene, the hidden image, what the decoder
gives on a student test view (the scene a viewer sees: no image), the student at the secret key (the image) and
the clean teacher at the key (nothing).

  python -m experiments.overview_figure
"""
from __future__ import annotations

import argparse
import pathlib

from conceal_jax.core import fileio

RUN = "conceal_recommended_w16"  # bench-conceal's row of the recommended recipe, decoder width 16
SCENES = ("lego", "beer")
PANELS = (("hidden.png", "hidden image"), ("normal_revealed.png", "decoder on a student\ntest view: the scene"),
          ("revealed.png", "decoder at the secret key:\nthe image revealed"),
          ("teacher_revealed.png", "decoder on the clean\nteacher at the key"))


def draw(results: pathlib.Path) -> pathlib.Path:
  """Draws the scenes that have the recommended run's images into results/overview.png; its path."""
  import imageio.v3 as iio
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  runs = [(scene, results / "revealed" / scene / RUN) for scene in SCENES
          if all((results / "revealed" / scene / RUN / name).is_file() for name, _ in PANELS)]
  if not runs:
    raise SystemExit(f"no images of {RUN} under {results / 'revealed'}: run make bench-conceal first")
  fig, axes = plt.subplots(len(runs), len(PANELS), figsize=(2.4 * len(PANELS), 2.6 * len(runs)), squeeze=False)
  for i, (scene, run) in enumerate(runs):
    for j, (name, title) in enumerate(PANELS):
      ax = axes[i][j]
      ax.imshow(iio.imread(run / name))
      ax.set_xticks([])
      ax.set_yticks([])
      if i == 0:
        ax.set_title(title, fontsize=9)
      if j == 0:
        ax.set_ylabel(scene, fontsize=11)
  path = results / "overview.png"
  fileio.save_figure(fig, path)
  plt.close(fig)
  return path


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--results", default="experiments/results")
  print(draw(pathlib.Path(parser.parse_args().results)))


if __name__ == "__main__":
  main()
