"""Typed settings from config sections: a frozen dataclass built from the keys of an ml_collections section
that name its fields, so no job copies config values by hand and each dataclass validates itself."""
from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")


def from_section(cls: type[T], section: Any, **overrides) -> T:
  """`cls(**fields)` with every field of `cls` present in `section` (a ConfigDict or dict), then
  `overrides`; keys of the section that are not fields are ignored (they belong to the job)."""
  names = {f.name for f in dataclasses.fields(cls)}
  items = section.items() if hasattr(section, "items") else {}
  values = {k: _plain(v) for k, v in items if k in names}
  values.update(overrides)
  return cls(**values)


def _plain(value: Any) -> Any:
  """ConfigDict lists come back as lists; a hashable (static) dataclass needs tuples."""
  return tuple(value) if isinstance(value, list) else value


def check_count(key: str, value: Any, minimum: int = 1) -> int:
  """`value` if it is an int (not a bool) >= minimum; otherwise ValueError naming the config `key`."""
  if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
    raise ValueError(f"{key} must be an integer >= {minimum}, got {value!r}")
  return value
