"""Prints the short summary of `make demo` from the metrics files in its workdir.

  python -m experiments.demo_summary workdirs/demo
"""
from __future__ import annotations

import json
import pathlib
import sys


def summary(root: pathlib.Path) -> str:
  read = lambda *parts: json.loads(root.joinpath(*parts).read_text())
  teacher, concealed = read("teacher", "metrics.json"), read("conceal", "metrics.json")
  revealed, clean = read("reveal", "reveal.json"), read("reveal_clean", "reveal.json")
  student = concealed["student_vs_ground_truth"]
  return "\n".join([
      f"teacher test PSNR {teacher['mean']['psnr']:.2f} dB  SSIM {teacher['mean']['ssim']:.4f}  "
      f"LPIPS {teacher['mean']['lpips']:.4f}",
      f"student test PSNR {student['psnr']:.2f} dB  SSIM {student['ssim']:.4f}  LPIPS {student['lpips']:.4f}  "
      f"(vs teacher renders {concealed['student_vs_teacher']['psnr']:.2f} dB)",
      f"hidden image at the check view: PSNR {concealed['hidden']['psnr']:.2f} dB  "
      f"SSIM {concealed['hidden']['ssim']:.4f}"
      f"  (reveal job: {revealed['psnr']:.2f} dB / {revealed['ssim']:.4f})",
      f"leakage SSIM: student test views max {concealed['leakage']['max_ssim_student_test_views']:.4f}, "
      f"clean teacher at the check view {clean['ssim']:.4f}, student near the check view (moved 2-5% of its depth, "
      f"2-5 degrees) max {concealed['leakage'].get('max_ssim_near_check', float('nan')):.4f}",
  ])


if __name__ == "__main__":
  print(summary(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "workdirs/demo")))
