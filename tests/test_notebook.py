"""The walkthrough notebook (experiments/conceal_walkthrough.ipynb) runs end to end in its tiny setting.

It is executed with nbclient on a python3 kernel of the interpreter running the tests (jupyter_client
launches a kernel spec whose argv starts with `python` with sys.executable, so the venv's ipykernel and
conceal_jax are the ones used; the notebook prints its interpreter and the test checks it).
"""
from __future__ import annotations

import json
import math
import os
import pathlib
import sys

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOK = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "conceal_walkthrough.ipynb"
SUMMARY_KEYS = {"teacher_psnr", "student_psnr", "student_vs_teacher_psnr", "hidden_psnr", "hidden_ssim",
                "leakage_max_ssim_student_test_views", "leakage_ssim_teacher_check_view", "num_test_views"}


def _text(cell) -> str:
  return "".join(out.get("text", "") for out in cell.get("outputs", []) if out.get("output_type") == "stream"
                 and out.get("name") == "stdout")


def test_committed_notebook_is_clean_and_parameterised():
  nb = nbformat.read(NOTEBOOK, as_version=4)
  nbformat.validate(nb)
  code = [cell for cell in nb.cells if cell.cell_type == "code"]
  assert all(not cell.outputs and cell.execution_count is None for cell in code), "clear the outputs"
  tagged = [i for i, cell in enumerate(code) if "parameters" in cell.metadata.get("tags", [])]
  assert tagged == [0], "the first code cell, and only it, is the papermill parameters cell"


@pytest.mark.slow
def test_walkthrough_runs_tiny(tmp_path, monkeypatch):
  workdir = tmp_path / "work"
  monkeypatch.setenv("CONCEAL_NB_TINY", "1")
  monkeypatch.setenv("CONCEAL_NB_WORKDIR", str(workdir))
  monkeypatch.setenv("CONCEAL_JAX_CACHE", str(tmp_path / "cache"))
  nb = nbformat.read(NOTEBOOK, as_version=4)
  client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=300,
                                   resources={"metadata": {"path": str(tmp_path)}})
  client.execute()  # raises CellExecutionError, with the traceback, if a cell fails

  code = [cell for cell in nb.cells if cell.cell_type == "code"]
  assert not [out for cell in code for out in cell.outputs if out.output_type == "error"]
  setup = _text(code[1])
  assert f"python: {sys.executable}" in setup, setup  # the kernel is this interpreter (the venv)
  assert f"workdir: {workdir}" in setup

  for name in ("teacher/point_cloud.ply", "conceal/student.ply", "conceal/decoder.msgpack", "conceal/key.json",
               "conceal/metrics.json"):
    assert (workdir / name).is_file(), name
  assert any("image/png" in out.get("data", {}) for cell in code for out in cell.outputs), "no figure shown"

  printed = _text(code[-1])
  assert printed.startswith("metrics summary:"), printed
  summary = json.loads(printed.split("\n", 1)[1])
  assert set(summary) == SUMMARY_KEYS
  assert summary["num_test_views"] == 1  # the tiny setting scores one test view
  report = json.loads((workdir / "conceal" / "metrics.json").read_text())
  assert summary["hidden_psnr"] == report["hidden"]["psnr"]
  assert summary["teacher_psnr"] == report["teacher_vs_ground_truth"]["psnr"]
  for name in SUMMARY_KEYS - {"num_test_views"}:
    assert isinstance(summary[name], float) and math.isfinite(summary[name]), name
  assert os.listdir(workdir / "demo_scene")
