"""The package's layer order (setup.cfg [importlinter]) holds: no module imports from a layer above it."""
from __future__ import annotations

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
