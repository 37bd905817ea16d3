"""ConcealGS beside StegaNeRF on one scene, the baselines issue's render-at-equal-hidden target as tables and one
plot for REPRODUCTION.md: runs of either (bench-conceal's ConcealGS rows, the paper's ablations aside, and
bench-baselines' StegaNeRF rows) at their render PSNR against ground truth, hidden PSNR at the key and worst
leakage, and for each StegaNeRF run the ConcealGS runs ahead of it (`ahead`); on their means over seeds
(`over_seeds`), since one seed's lead can sit within a recipe's seed spread. REPRODUCTION.md shows the recipes'
means in its body (`recipe_table`) and every run (`table`, `seed_table`) in its appendix.
"""
from __future__ import annotations

import pathlib
import re

import numpy as np

from conceal_jax.core import fileio
from experiments import results_io


# Both benches name a row that reruns another row's settings from seed N `<that row>_seed<N>` (tested).
_SEED = re.compile(r"_seed(\d+)")


def recipe(row: str) -> tuple[str, int]:
  """A bench row's name -> the row whose settings it runs and its seed (0 unless the name says another)."""
  found = _SEED.search(row)
  return (row, 0) if found is None else (row[:found.start()] + row[found.end():], int(found.group(1)))


def points(conceal_rows: list[dict], baseline_rows: list[dict]) -> list[dict]:
  """bench-conceal rows (ConcealGS) and bench-baselines rows of one scene (both benches' summary rows, with their
  student_psnr_loss and max_leakage) -> one point per ConcealGS or StegaNeRF run: method, run (the row's name and
  where it ran), recipe and seed (`recipe`), width (of the decoder), steps (joint + decoder polish) and length (the
  same in words), render_psnr, render_loss (teacher minus student, dB), hidden_psnr, max_leakage (SSIM)."""
  def point(method, row, run, width, steps, length):
    name, seed = recipe(row["row"])
    return dict(method=method, run=run, recipe=name, seed=seed, width=width, steps=steps, length=length,
                render_psnr=row["student_vs_ground_truth"]["psnr"], render_loss=row["student_psnr_loss"],
                hidden_psnr=row["hidden"]["psnr"], max_leakage=row["max_leakage"])
  ours = [point("ConcealGS", r, f"{r['row']}{results_io.on_device(r)}", r["decoder_width"],
                r["iterations"] + r.get("decoder_polish_steps", 0), results_io.conceal_steps(r)) for r in conceal_rows]
  theirs = [point("StegaNeRF", r, r["row"], r["steganerf"]["settings"]["decoder_width"], r["iterations"],
                  str(r["iterations"])) for r in baseline_rows if r.get("method") == "StegaNeRF"]
  return ours + theirs


def ahead(ours: dict, theirs: dict) -> bool:
  """The baselines issue's target for one pair of `points`: the ConcealGS run renders better than the StegaNeRF run
  at equal or better hidden PSNR, with a decoder as wide and in no more steps."""
  return (ours["width"] == theirs["width"] and ours["steps"] <= theirs["steps"]
          and ours["render_psnr"] > theirs["render_psnr"] and ours["hidden_psnr"] >= theirs["hidden_psnr"])


def over_seeds(runs: list[dict], min_seeds: int = 2) -> list[dict]:
  """`points` -> one point per recipe run from `min_seeds` or more seeds (same method, recipe, decoder width and steps):
  its render_psnr, render_loss and hidden_psnr averaged over the seeds, hidden_range (lowest, highest), its worst
  max_leakage, and seeds (sorted); its run is the recipe's name."""
  groups: dict[tuple, list[dict]] = {}
  for p in runs:
    groups.setdefault((p["method"], p["recipe"], p["width"], p["steps"]), []).append(p)
  means = []
  for (method, name, width, steps), group in groups.items():
    seeds = sorted(p["seed"] for p in group)
    if len(set(seeds)) < min_seeds:
      continue
    mean = {k: float(np.mean([p[k] for p in group])) for k in ("render_psnr", "render_loss", "hidden_psnr")}
    hidden = [p["hidden_psnr"] for p in group]
    means.append(dict(mean, method=method, run=name, recipe=name, width=width, steps=steps,
                      length=group[0]["length"], seeds=seeds, hidden_range=(min(hidden), max(hidden)),
                      max_leakage=max(p["max_leakage"] for p in group)))
  return means


def _render(entry: dict) -> str:
  return f"{entry['render_psnr']:.2f} ({-entry['render_loss']:+.2f})"


def _hidden(mean: dict) -> str:
  """A mean's hidden PSNR, with its range (lowest-highest) where it is over two or more seeds."""
  low, high = mean["hidden_range"]
  return f"{mean['hidden_psnr']:.2f}" + (f" ({low:.2f}-{high:.2f})" if len(mean["seeds"]) > 1 else "")


def _lines(entries: list[dict], middle) -> list[str]:
  """One table line per point or recipe mean of `entries`, StegaNeRF's first and each by falling hidden PSNR:
  method, run, width, steps, `middle(entry)`'s cells, max leakage, and for StegaNeRF's the ConcealGS ones `ahead`."""
  ours = [e for e in entries if e["method"] == "ConcealGS"]
  lines = []
  for e in sorted(entries, key=lambda e: (e["method"] != "StegaNeRF", -e["hidden_psnr"])):
    beaten_by = "; ".join(o["run"] for o in ours if ahead(o, e)) or "none"
    lines.append(f"| {e['method']} | {e['run']} | {e['width']} | {e['length']} | {middle(e)} | {e['max_leakage']:.3f} "
                 f"| {beaten_by if e['method'] == 'StegaNeRF' else ''} |")
  return lines


def _means_lines(title: str, blurb: str, means: list[dict], empty: str) -> list[str]:
  """`over_seeds` means as REPRODUCTION.md lines under `title`, each StegaNeRF recipe with the ConcealGS recipes
  `ahead` of it on the means; `empty`'s line when there is none."""
  lines = [f"### {title}", "", blurb, "",
           "| method | recipe | width | steps | seeds | render PSNR (student - teacher) | hidden PSNR | max leakage | "
           "ConcealGS recipes ahead |", "|---|---|---|---|---|---|---|---|---|"]
  lines += _lines(means, lambda m: f"{', '.join(map(str, m['seeds']))} | {_render(m)} | {_hidden(m)}")
  if not means:
    lines.append(f"| {empty} | | | | | | | | |")
  return lines + [""]


AHEAD_RULE = ("A ConcealGS recipe is ahead of a StegaNeRF one when its mean render PSNR is higher and its mean hidden "
              "PSNR at least as high, with a decoder as wide and in no more steps. Max leakage is the highest SSIM to "
              "I that the decoder reveals away from the key (student test views, clean teacher at the key, near the "
              "key), worst over the seeds.")


def recipe_table(scene: str, means: list[dict]) -> list[str]:
  """Means over seeds (`over_seeds`, one seed enough) of the recipes and of StegaNeRF's rows, as REPRODUCTION.md
  lines."""
  return _means_lines(f"The recipes beside StegaNeRF ({scene}): which render better at equal or better hidden PSNR",
                      "Each recipe and each StegaNeRF row at the recipes' length, the mean of its seeds (hidden PSNR: "
                      "mean, lowest-highest over two or more seeds). " + AHEAD_RULE, means, "not run yet")


def seed_table(scene: str, runs: list[dict], title: str = "") -> list[str]:
  """`over_seeds` of `points` as REPRODUCTION.md lines, each StegaNeRF recipe with the ConcealGS recipes `ahead` of
  it on the means."""
  return _means_lines(title or f"On the means over seeds ({scene})",
                      "Rows run from two or more seeds, each the mean of its runs (hidden PSNR: mean, lowest-highest). "
                      + AHEAD_RULE, over_seeds(runs), "no recipe run from two seeds yet")


def table(scene: str, runs: list[dict], title: str = "") -> list[str]:
  """`points` as REPRODUCTION.md lines, StegaNeRF's runs first, each with the ConcealGS runs `ahead` of it."""
  title = title or f"ConcealGS beside StegaNeRF ({scene}): which runs render better at equal or better hidden PSNR"
  lines = [f"### {title}", "",
           "Every run of either on this scene. A ConcealGS run is ahead of a StegaNeRF run when its render PSNR is "
           "higher and its hidden PSNR at least as high, with a decoder as wide and in no more steps. Max leakage is "
           "the highest SSIM to I that the decoder reveals away from the key (student test views, clean teacher "
           "at the key, near the key).", "",
           "| method | run | width | steps | render PSNR (student - teacher) | hidden PSNR | max leakage | "
           "ConcealGS runs ahead |", "|---|---|---|---|---|---|---|---|"]
  lines += _lines(runs, lambda p: f"{_render(p)} | {p['hidden_psnr']:.2f}")
  if not runs:
    lines.append("| not run yet | | | | | | | |")
  return lines + [""]


def figure(scene: str, runs: list[dict], results: pathlib.Path) -> str | None:
  """`points` as a scatter, render loss against hidden PSNR, coloured by max leakage, to tradeoff_<scene>.png in
  `results`; its name, or None when there is no run of either method."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  if not runs:
    return None
  fig, ax = plt.subplots(figsize=(9, 6))
  for method, marker in (("ConcealGS", "o"), ("StegaNeRF", "^")):
    mine = [p for p in runs if p["method"] == method]
    drawn = ax.scatter([p["render_loss"] for p in mine], [p["hidden_psnr"] for p in mine], marker=marker, s=60,
                       c=[p["max_leakage"] for p in mine], cmap="viridis", vmin=0.0, vmax=1.0, label=method,
                       edgecolors="black")
    for p in mine:
      ax.annotate(f"{p['run']}, w{p['width']}", (p["render_loss"], p["hidden_psnr"]), fontsize=6,
                  xytext=(4, 2), textcoords="offset points")
  fig.colorbar(drawn, ax=ax, label="max leakage (SSIM to I away from the key)")
  ax.set_xlabel("render PSNR loss to the teacher (dB; left is better)")
  ax.set_ylabel("hidden PSNR at the key (dB; up is better)")
  ax.set_title(f"{scene}: ConcealGS and StegaNeRF")
  ax.legend(loc="best")
  ax.grid(alpha=0.3)
  name = f"tradeoff_{scene}.png"
  fileio.save_figure(fig, results / name)
  plt.close(fig)
  return name
