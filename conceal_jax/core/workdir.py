"""A workdir holds one run: its config.json records the settings that shaped it, and running the workdir
again with any of them changed is refused, so a resumed checkpoint is never trained on by another run.

Settings that only change what is shown or how often it is saved (PRESENTATION_KEYS) may differ, and a setting
added to the code since the run was saved is no change when it is at its default (the run ran as the default does);
one removed since is no change when the run had it at the value the code now always has (`retired`).
"""
from __future__ import annotations

import json
import os

from conceal_jax.core import fileio

CONFIG_FILE = "config.json"
# Leaf names of settings that leave a run's result unchanged: logging, progress bars, checkpoint cadence, and a
# time limit (where one process stops; the finished run is the same).
PRESENTATION_KEYS = frozenset({"progress_bar", "log_every", "checkpoint_every", "time_limit_min"})


def flatten(tree: dict, prefix: str = "") -> dict:
  """{'a.b.c': value} for every leaf of a nested dict."""
  flat = {}
  for name, value in tree.items():
    path = f"{prefix}{name}"
    flat.update(flatten(value, path + ".") if isinstance(value, dict) else {path: value})
  return flat


def with_defaults(saved: dict, defaults: dict) -> dict:
  """`saved` (a run's config.json) with the keys `defaults` holds and it lacks (those added since it was written)
  at their default values."""
  merged = dict(defaults)
  for name, value in saved.items():
    below = defaults.get(name)
    merged[name] = with_defaults(value, below) if isinstance(value, dict) and isinstance(below, dict) else value
  return merged


def differing_keys(saved: dict, config: dict, defaults: dict | None = None, retired: dict | None = None) -> list[str]:
  """The dotted keys whose values differ between two configs (missing on one side counts, except a key `saved`
  lacks that `config` holds at its value in `defaults`, and a dotted key `config` lacks that `saved` holds at its
  value in `retired`), ignoring PRESENTATION_KEYS; lists and tuples compare alike (JSON stores tuples as lists)."""
  a, b = (flatten(json.loads(json.dumps(tree))) for tree in (saved, config))
  d = flatten(json.loads(json.dumps(defaults or {})))
  added_at_default = lambda k: k not in a and k in d and b.get(k) == d[k]
  retired_at_value = lambda k: k not in b and k in (retired or {}) and a.get(k) == retired[k]
  return sorted(k for k in a.keys() | b.keys()
                if k.rsplit(".", 1)[-1] not in PRESENTATION_KEYS and a.get(k, "<absent>") != b.get(k, "<absent>")
                and not added_at_default(k) and not retired_at_value(k))


def claim(workdir: str, config: dict, resumable: bool = True, defaults: dict | None = None,
          retired: dict | None = None) -> None:
  """Writes `config` as workdir/config.json; for a `resumable` run (one that continues from the checkpoints
  it finds), ValueError naming the differing keys (differing_keys, with the code's `defaults` and `retired`) if
  the workdir already holds a run of other settings (nothing is written then). A run that is not resumable
  replaces what it writes whole."""
  path = os.path.join(workdir, CONFIG_FILE)
  if resumable and os.path.isfile(path):
    with open(path) as f:
      try:
        saved = json.load(f)
      except ValueError as error:
        raise ValueError(f"{path} is not a readable config ({error}); remove it to start a fresh run") from error
    differ = differing_keys(saved, config, defaults, retired)
    if differ:
      shown = ", ".join(differ[:8]) + (f" and {len(differ) - 8} more" if len(differ) > 8 else "")
      raise ValueError(f"{workdir} holds a run with other settings ({shown} differ); run it with the same settings "
                       "to resume it, or choose a new workdir (or remove this one) to start fresh")
  fileio.write_json(path, config)
