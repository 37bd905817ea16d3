"""The package's layer order (setup.cfg [importlinter]) holds: no module imports from a layer above it; and
every source line fits the line limit."""
from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_import_contracts_are_kept():
  lint = os.path.join(os.path.dirname(sys.executable), "lint-imports")
  if not os.path.exists(lint):
    lint = shutil.which("lint-imports")
  if lint is None:
    pytest.fail("import-linter is not installed (it is in the [test] extra)")
  result = subprocess.run([lint, "--config", "setup.cfg", "--no-cache"], cwd=ROOT, capture_output=True,
                          text=True, check=False)
  assert result.returncode == 0, result.stdout + result.stderr
  assert "0 broken" in result.stdout


MAX_LINE = 120  # the project's line limit (2-space indent), as the style guide sets it


def test_source_lines_fit_the_limit():
  long_lines = []
  for top in ("conceal_jax", "experiments", "tests"):
    for folder, _, files in os.walk(os.path.join(ROOT, top)):
      for name in (f for f in files if f.endswith(".py")):
        path = os.path.join(folder, name)
        with open(path, encoding="utf-8") as f:
          long_lines += [f"{os.path.relpath(path, ROOT)}:{i}" for i, line in enumerate(f, 1)
                         if len(line.rstrip("\n")) > MAX_LINE]
  assert not long_lines, f"lines over {MAX_LINE} characters: {long_lines}"


MAX_CONCEAL_MODULE_LINES = 250  # the concealment layer's modules stay small and single-purpose (issue 38)
MAX_CONCEAL_FUNCTION_LINES = 60


def test_conceal_modules_and_functions_stay_small():
  too_long = []
  folder = os.path.join(ROOT, "conceal_jax", "conceal")
  for name in sorted(f for f in os.listdir(folder) if f.endswith(".py")):
    with open(os.path.join(folder, name), encoding="utf-8") as f:
      source = f.read()
    if source.count("\n") > MAX_CONCEAL_MODULE_LINES:
      too_long.append(f"{name}: {source.count(chr(10))} lines")
    for node in ast.walk(ast.parse(source)):
      if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        length = node.end_lineno - node.lineno + 1
        if length > MAX_CONCEAL_FUNCTION_LINES:
          too_long.append(f"{name}:{node.lineno} {node.name}: {length} lines")
  assert not too_long, (f"conceal/ modules over {MAX_CONCEAL_MODULE_LINES} lines or functions over "
                        f"{MAX_CONCEAL_FUNCTION_LINES}: {too_long}")
