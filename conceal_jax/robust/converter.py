"""Publishing round trips through the ecosystem's converter, @playcanvas/splat-transform (the converter
behind SuperSplat; `make node_modules` installs it into ./node_modules, and it runs offline on the CPU with
`-g cpu`).

A scene is written as a standard 3D-GS `.ply`, converted by `splat-transform -w -g cpu in.ply [actions]
out.<format>` and, for the compressed formats, converted back to `.ply`, then read with data.ply (whose
reader accepts the converter's property order and clips the infinite opacity logits it writes after a
`.compressed.ply`). Formats: `ply`, `sog` (SuperSplat's web format), `spz` (Niantic's), `compressed.ply`
(PlayCanvas's quantised chunks). Actions: decimation to a fraction of the Gaussians, SH bands cut, floater
filtering (`-F`: Gaussians contributing to no solid voxel removed). The converter voxelises on a WebGPU adapter
only, so floater filtering runs on `-g <adapter>` (GPU_ENV_VAR, default the first adapter listed): a GPU, or on a
machine without one mesa's lavapipe, a Vulkan device on the CPU (`make webgpu-cpu` installs it on Debian).
"""
from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess
import tempfile
from typing import Sequence

from conceal_jax.data import ply
from conceal_jax.splat.gaussians import Gaussians

FORMATS = ("ply", "sog", "spz", "compressed.ply")
# The environment variable naming another splat-transform executable.
ENV_VAR = "CONCEAL_JAX_SPLAT_TRANSFORM"
# The environment variable naming the WebGPU adapter (an index of `splat-transform --list-gpus`) of the GPU-only
# actions; unset: the first adapter listed.
GPU_ENV_VAR = "CONCEAL_JAX_SPLAT_TRANSFORM_GPU"
_REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
_TIMEOUT_S = 600


class ConverterError(RuntimeError):
  """splat-transform is missing or failed."""


def executable() -> pathlib.Path | None:
  """The splat-transform executable: $CONCEAL_JAX_SPLAT_TRANSFORM, else the repository's
  node_modules/.bin/splat-transform; None when neither exists (tests then skip)."""
  candidates = [os.environ.get(ENV_VAR), _REPO_ROOT / "node_modules" / ".bin" / "splat-transform"]
  for candidate in candidates:
    if candidate and os.path.isfile(candidate) and os.access(candidate, os.X_OK):
      return pathlib.Path(candidate)
  return None


def available() -> bool:
  """Whether splat-transform and a `node` to run it are installed."""
  return executable() is not None and shutil.which("node") is not None


def _call(arguments: Sequence[str], timeout_s: float) -> str:
  """splat-transform's output (stdout) for `arguments`. ConverterError with its output when it is missing or
  fails."""
  path = executable()
  if path is None:
    raise ConverterError(f"splat-transform is not installed: run `make node_modules` or set {ENV_VAR}")
  command = [str(path), *map(str, arguments)]
  try:
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False)
  except (OSError, subprocess.TimeoutExpired) as e:
    raise ConverterError(f"{' '.join(command)}: {e}") from e
  if result.returncode != 0:
    raise ConverterError(f"{' '.join(command)} failed ({result.returncode}): "
                         f"{(result.stderr or result.stdout).strip()[-2000:]}")
  return result.stdout


def run(arguments: Sequence[str], timeout_s: float = _TIMEOUT_S, device: str = "cpu") -> None:
  """Runs `splat-transform -q -w -g <device> <arguments>` (quiet, overwrite; device "cpu": no WebGPU, else an
  adapter's index). ConverterError with its output when it is missing or fails."""
  _call(["-q", "-w", "-g", device, *arguments], timeout_s)


def adapters(timeout_s: float = 120) -> list[str]:
  """The WebGPU adapters splat-transform finds (`--list-gpus`), by index; [] where there is none or no
  converter."""
  try:
    listing = _call(["--list-gpus"], timeout_s)
  except ConverterError:
    return []
  return [m.group(1).strip() for m in re.finditer(r"^\[\d+\] (.+)$", listing, re.MULTILINE)]


def gpu_device() -> str:
  """The adapter index of the GPU-only actions: $CONCEAL_JAX_SPLAT_TRANSFORM_GPU, else "0". ConverterError where
  splat-transform lists no adapter, or none at that index."""
  found = adapters()
  if not found:
    raise ConverterError("floater filtering needs a WebGPU adapter and splat-transform lists none: on a machine "
                         "without a GPU, `make webgpu-cpu` installs mesa's lavapipe (a Vulkan device on the CPU)")
  device = os.environ.get(GPU_ENV_VAR, "0")
  if not (device.isdigit() and int(device) < len(found)):
    listing = ", ".join(f"{i}: {name}" for i, name in enumerate(found))
    raise ConverterError(f"${GPU_ENV_VAR}={device!r} is not an adapter index splat-transform lists ({listing})")
  return device


def actions(decimate: float | None = None, sh_degree: int | None = None, floaters: bool = False) -> list[str]:
  """splat-transform actions: decimation to the fraction `decimate` of the Gaussians (in (0, 1]),
  SH bands above `sh_degree` removed (0..3) and, with `floaters`, floater filtering at the converter's defaults."""
  out = ["-F"] if floaters else []
  if sh_degree is not None:
    if sh_degree not in (0, 1, 2, 3):
      raise ValueError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree}")
    out += ["-H", str(sh_degree)]
  if decimate is not None:
    if not 0 < decimate <= 1:
      raise ValueError(f"decimate must be a fraction in (0, 1], got {decimate}")
    out += ["-d", f"{100 * decimate:g}%"]
  return out


def round_trip(gaussians: Gaussians, fmt: str = "ply", *, decimate: float | None = None,
               sh_degree: int | None = None, floaters: bool = False, workdir: str | os.PathLike | None = None,
               timeout_s: float = _TIMEOUT_S) -> Gaussians:
  """`gaussians` written as .ply, converted to `fmt` with the actions (see `actions`), read back.

  workdir: where the intermediate files go (kept there); None: a temporary folder, removed after.
  timeout_s: per converter call (.sog's clustering of a scene of 100k Gaussians takes many minutes on a CPU).
  floaters: floater filtering, on gpu_device()'s adapter.
  ValueError for an unknown format or bad action; ConverterError when splat-transform fails (or, for floater
  filtering, finds no adapter)."""
  if fmt not in FORMATS:
    raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
  steps = actions(decimate, sh_degree, floaters)
  if workdir is None:
    with tempfile.TemporaryDirectory(prefix="splat_transform_") as tmp:
      return round_trip(gaussians, fmt, decimate=decimate, sh_degree=sh_degree, floaters=floaters, workdir=tmp,
                        timeout_s=timeout_s)
  device = gpu_device() if floaters else "cpu"  # before anything is written: no adapter, no folder
  folder = pathlib.Path(workdir)
  folder.mkdir(parents=True, exist_ok=True)
  source, converted = folder / "in.ply", folder / f"out.{fmt}"
  ply.save_ply(source, gaussians)
  run([source, *steps, converted], timeout_s, device)
  if fmt == "ply":
    return ply.load_ply(converted)
  back = folder / "back.ply"
  run([converted, back], timeout_s)
  return ply.load_ply(back)
