"""Atomic file writes: a reader (or a crash) never sees a half-written file.

Everything is written to a temporary file in the destination folder and renamed over the target,
which POSIX guarantees to be atomic within one filesystem.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from typing import Any, Iterator

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
  """Yields a temporary path next to `path`; on success it replaces `path`, on error it is removed."""
  path = os.fspath(path)
  folder = os.path.dirname(os.path.abspath(path))
  os.makedirs(folder, exist_ok=True)
  suffix = os.path.splitext(path)[1]  # keep the extension: some writers pick the format from it
  fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=suffix)
  os.close(fd)
  try:
    yield tmp
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file normal permissions
    os.replace(tmp, path)
  except BaseException:
    with contextlib.suppress(FileNotFoundError):
      os.remove(tmp)
    raise


def _umask() -> int:
  mask = os.umask(0)
  os.umask(mask)
  return mask


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  with atomic_path(path) as tmp, open(tmp, "wb") as f:
    f.write(data)


def copy_file(source: str | os.PathLike, path: str | os.PathLike) -> None:
  """Copies `source` to `path` without reading it into memory; `path` is never left half-written."""
  with atomic_path(path) as tmp:
    shutil.copyfile(source, tmp)


def write_text(path: str | os.PathLike, text: str) -> None:
  write_bytes(path, text.encode())


def write_json(path: str | os.PathLike, obj: Any) -> None:
  write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True, default=json_default) + "\n").encode())


def write_image(path: str | os.PathLike, image: Any) -> None:
  """Writes a float image in [0, 1] ([H, W] or [H, W, C]) as 8-bit PNG."""
  import imageio.v3 as iio
  pixels = np.clip(np.asarray(image, np.float64), 0.0, 1.0)
  with atomic_path(path) as tmp:
    iio.imwrite(tmp, np.round(pixels * 255).astype(np.uint8))


def json_default(value: Any) -> Any:
  if isinstance(value, (np.generic, np.ndarray)) or hasattr(value, "__array__"):
    return np.asarray(value).tolist()
  raise TypeError(f"cannot write {type(value).__name__} to JSON")


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 120, palette: int = 0) -> None:
  """Saves a matplotlib figure atomically (a reader never sees a half-written plot). `palette` > 0 stores the PNG
  with at most that many colours: a chart of flat colours keeps its look at a third of the bytes (a photo does not)."""
  fig.tight_layout()
  with atomic_path(path) as tmp:
    # tight_layout leaves out the titles of axes turned off (image grids); the tight box takes them in
    fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    if palette:
      from PIL import Image
      with Image.open(tmp) as image:
        image = image.convert("RGB").quantize(colors=palette)
      image.save(tmp, optimize=True)
