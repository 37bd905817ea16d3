"""The benchmarks' result files: rows merged into <out>/<name>.json, rewritten with their table and plot,
so a benchmark can run one scene or row at a time and a stopped benchmark keeps what it finished."""
from __future__ import annotations

import json
import pathlib
import platform
from typing import Callable

import jax

from conceal_jax.core import fileio


def merged_rows(path: pathlib.Path, rows: list[dict], key: Callable[[dict], tuple]) -> list[dict]:
  """The rows already in `path`, each replaced in place by the row of `rows` with its key(row) (so a rebuilt
  row keeps its place in the table and plot), then the rows of `rows` that are new, in their order."""
  try:
    old = json.loads(path.read_text())["rows"]
  except (OSError, ValueError, KeyError):
    old = []
  fresh = {key(r): r for r in rows}
  kept = [fresh.pop(key(r), r) for r in old]
  return kept + list(fresh.values())


def results_json(header: dict, rows: list[dict]) -> str:
  """{**header, "rows": rows} as JSON text, the header indented and one row per line: a result file stays small
  (rows carry nested matrices that an indented dump spreads over dozens of lines) and its diff shows which rows
  changed."""
  fields = [f"  {json.dumps(k)}: " + json.dumps(v, indent=2, sort_keys=True, default=fileio.json_default)
            .replace("\n", "\n  ") for k, v in sorted(header.items())]
  lines = [json.dumps(row, sort_keys=True, default=fileio.json_default) for row in rows]
  fields.append('  "rows": [' + "".join(f"\n    {line}," for line in lines).rstrip(",") + ("\n  ]" if rows else "]"))
  return "{\n" + ",\n".join(fields) + "\n}\n"


def write_results(out: pathlib.Path, name: str, rows: list[dict], key: Callable[[dict], tuple],
                  table: Callable[[list[dict]], str], plot: Callable[[list[dict], pathlib.Path], None],
                  **header) -> list[dict]:
  """Merges `rows` into <out>/<name>.json (with the device, the CPU and `header`), rewrites <name>.md
  and <name>.png from all rows; returns them."""
  merged = merged_rows(out / f"{name}.json", rows, key)
  fileio.write_text(out / f"{name}.json", results_json(dict(device=str(jax.devices()[0]), cpu=platform.processor(),
                                                            **header), merged))
  fileio.write_text(out / f"{name}.md", table(merged))
  plot(merged, out / f"{name}.png")
  return merged


# A run's images that REPRODUCTION.md's figure shows (label -> file in the run's folder). The benches keep a copy
# under <out>/IMAGES_DIR, beside the JSON, since a workdir does not outlive the machine it ran on.
IMAGES_DIR = "revealed"
CONCEAL_IMAGES = {"hidden": "hidden.png", "student, key": "revealed.png", "clean teacher, key": "teacher_revealed.png",
                  "student, test view": "normal_revealed.png"}
BASELINE_IMAGES = {"revealed": "revealed.png"}


def keep_images(out: pathlib.Path, run_dir: pathlib.Path, names: dict[str, str]) -> dict[str, str]:
  """Copies the images `names` of `run_dir` (<workdir>/<scene>/<run>) that exist to <out>/IMAGES_DIR/<scene>/<run>/;
  {label: its path relative to `out`} (a bench row's `images`)."""
  kept = {}
  for label, name in names.items():
    if (run_dir / name).is_file():
      relative = pathlib.Path(IMAGES_DIR) / run_dir.parent.name / run_dir.name / name
      fileio.copy_file(run_dir / name, out / relative)
      kept[label] = str(relative)
  return kept


def row_images(results: pathlib.Path, row: dict, run_dir: pathlib.Path, names: dict[str, str]) -> list[tuple]:
  """[(label, path)] of a bench row's images that exist, in the order of `names`: the copies kept under `results`
  (its `images`, whose keys the JSON file holds sorted), or for a row written before the benches kept them, the
  files in its run's folder."""
  kept = row.get("images")
  files = [(label, results / kept[label]) for label in names if label in kept] if kept is not None else \
      [(label, run_dir / name) for label, name in names.items()]
  return [(label, path) for label, path in files if path.is_file()]


LEAKAGE_KEYS = ("max_ssim_student_test_views", "ssim_teacher_check_view", "max_ssim_near_check")


def conceal_steps(row: dict) -> str:
  """A bench-conceal row's length: its joint steps, and its decoder polish's where it has one."""
  polish = row.get("decoder_polish_steps", 0)
  return f"{row['iterations']}" + (f" + {polish} polish" if polish else "")


def on_device(row: dict) -> str:
  """' (H100)'-style note for a row whose steps ran on an accelerator (its `step_devices`, core.loop), '' for rows
  run on this CPU (also those from before the loop kept the device)."""
  kinds = [name.split(": ", 1)[-1] for name in row.get("step_devices", []) if not name.startswith("cpu")]
  return f" ({', '.join(kinds)})" if kinds else ""


def leakage_cells(leakage: dict, sep: str = " / ") -> str:
  """A metrics.json `leakage` dict as 'test views / clean teacher / near key' (nan where a figure is missing)."""
  return sep.join(f"{leakage.get(key, float('nan')):.3f}" for key in LEAKAGE_KEYS)
