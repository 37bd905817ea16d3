"""ConcealGS beside StegaNeRF on one scene, the baselines issue's render-at-equal-hidden target as one table and one
plot for REPRODUCTION.md: every run of either (bench-conceal's ConcealGS rows, the paper's ablations aside, and
bench-baselines' StegaNeRF rows) at its render PSNR against ground truth, its hidden PSNR at the key and its worst
leakage, and for each StegaNeRF run the ConcealGS runs ahead of it (`ahead`).
"""
from __future__ import annotations

import pathlib

from conceal_jax.core import fileio
from experiments import results_io


def points(conceal_rows: list[dict], baseline_rows: list[dict]) -> list[dict]:
  """bench-conceal rows (ConcealGS) and bench-baselines rows of one scene (both benches' summary rows, with their
  student_psnr_loss and max_leakage) -> one point per ConcealGS or StegaNeRF run: method, run (the row's name and
  where it ran), width (of the decoder), steps (joint + decoder polish) and length (the same in words), render_psnr,
  render_loss (teacher minus student, dB), hidden_psnr, max_leakage (SSIM)."""
  def point(method, row, run, width, steps, length):
    return dict(method=method, run=run, width=width, steps=steps, length=length,
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


def table(scene: str, runs: list[dict]) -> list[str]:
  """`points` as REPRODUCTION.md lines, StegaNeRF's runs first, each with the ConcealGS runs `ahead` of it."""
  lines = [f"### ConcealGS beside StegaNeRF ({scene}): which runs render better at equal or better hidden PSNR", "",
           "Every run of either on this scene. A ConcealGS run is ahead of a StegaNeRF run when its render PSNR is "
           "higher and its hidden PSNR at least as high, with a decoder as wide and in no more steps. Max leakage is "
           "the highest SSIM to I that the decoder reveals away from the key (student test views, clean teacher "
           "at the key, near the key).", "",
           "| method | run | width | steps | render PSNR (student - teacher) | hidden PSNR | max leakage | "
           "ConcealGS runs ahead |", "|---|---|---|---|---|---|---|---|"]
  ours = [p for p in runs if p["method"] == "ConcealGS"]
  for p in sorted(runs, key=lambda p: (p["method"] != "StegaNeRF", -p["hidden_psnr"])):
    beaten_by = "; ".join(o["run"] for o in ours if ahead(o, p)) or "none"
    lines.append(f"| {p['method']} | {p['run']} | {p['width']} | {p['length']} | {p['render_psnr']:.2f} "
                 f"({-p['render_loss']:+.2f}) | {p['hidden_psnr']:.2f} | {p['max_leakage']:.3f} | "
                 f"{beaten_by if p['method'] == 'StegaNeRF' else ''} |")
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
  ax.set_title(f"{scene}: ConcealGS and StegaNeRF runs")
  ax.legend(loc="lower right")
  ax.grid(alpha=0.3)
  name = f"tradeoff_{scene}.png"
  fileio.save_figure(fig, results / name)
  plt.close(fig)
  return name
