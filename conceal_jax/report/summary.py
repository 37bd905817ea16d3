"""What the command line prints when a job ends: a few lines saying what it wrote and its headline figures.

The logs above it are the job's progress; these lines are what a user reads to know what they got and where
it is. A conceal or verify run first writes its report page (run_report), which the summary names.
"""
from __future__ import annotations

import os

import ml_collections

from conceal_jax.conceal import reveal, train as conceal_train
from conceal_jax.gs import evaluate, train
from conceal_jax.report import run_report
from conceal_jax.robust import ownership


def _time(result: dict) -> str:
  """The steps' wall time (over resumes) and the median step time, as core.loop.LoopResult.timing gives them."""
  step = result["median_step_s"]
  return f"{result['wall_time_s']:.0f} s" + (f" ({step:.3g} s a step)" if step is not None else "")


def train_lines(workdir: str, result: dict) -> list[str]:
  test = result["test"]
  return [f"trained {result['iterations']} steps in {_time(result)}: {result['num_gaussians']} Gaussians",
          f"  test views: PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f}, LPIPS {test['lpips']:.4f}",
          f"  wrote {os.path.join(workdir, evaluate.SCENE_FILE)} (the scene), {train.TRAIN_FILE}, "
          f"{evaluate.METRICS_FILE}, test_renders/"]


def conceal_lines(workdir: str, result: dict) -> list[str]:
  m = result["metrics"]
  student, teacher = m["student_vs_ground_truth"], m["teacher_vs_ground_truth"]
  leakage = m["leakage"]
  return [f"concealed in {result['iterations']} steps, {_time(result)}: {result['num_gaussians']} Gaussians",
          f"  hidden image at the key: PSNR {m['hidden']['psnr']:.2f} dB, SSIM {m['hidden']['ssim']:.4f}",
          f"  student test PSNR {student['psnr']:.2f} dB (teacher {teacher['psnr']:.2f} dB; "
          f"{m['student_vs_teacher']['psnr']:.2f} dB to the teacher's renders)",
          f"  leakage SSIM: test views {leakage['max_ssim_student_test_views']:.3f}, clean teacher at the key "
          f"{leakage['ssim_teacher_check_view']:.3f}, near the key {leakage['max_ssim_near_check']:.3f}",
          *message_lines(m),
          f"  share {os.path.join(workdir, conceal_train.STUDENT_FILE)}; keep "
          f"{os.path.join(workdir, conceal_train.DECODER_FILE)} and "
          f"{os.path.join(workdir, conceal_train.KEY_FILE)} secret"]


def message_lines(result: dict) -> list[str]:
  """A message-mode key's reading (conceal.message.read_message), none otherwise."""
  if "message" not in result:
    return []
  m = result["message"]
  decoded = f"decoded {m['decoded']}" if m["decoded"] is not None else "not decodable (more errors than it corrects)"
  return [f"  message ({m['bits']} bits, {m['code']}): raw bit accuracy {m['raw_bit_accuracy']:.4f} "
          f"(binomial p 1e{m['log10_p_binomial']:.1f}), {decoded}, "
          f"{'the message hidden' if m['message_exact'] else 'not the message hidden ' + m['message']}"]


def reveal_lines(workdir: str, result: dict) -> list[str]:
  scores = (f": PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f} to the hidden image" if "psnr" in result
            else "")
  return [f"revealed from {result['ply']}{scores}", *message_lines(result),
          f"  wrote {os.path.join(workdir, 'revealed.png')}, {reveal.REVEAL_FILE}"]


def verify_lines(workdir: str, result: dict) -> list[str]:
  return [f"{result['ply']}: {'OWNED' if result['owned'] else 'not owned'}",
          f"  evidence: {run_report.evidence_figures(result)}", *message_lines(result),
          f"  wrote {os.path.join(workdir, ownership.VERIFY_FILE)}, revealed.png"]


LINES = {"train": train_lines, "conceal": conceal_lines, "reveal": reveal_lines, "verify": verify_lines}


def after_job(config: ml_collections.ConfigDict, workdir: str, result: dict) -> str:
  """The closing summary of the job config.mode that returned `result` in workdir ('' for a mode without one, or
  a run stopped early); a conceal or verify run's report.html is written first."""
  if config.mode not in LINES or "stopped_at" in result:
    return ""
  lines = LINES[config.mode](workdir, result)
  if config.mode in run_report.REPORTS:
    path, viewer_note = run_report.write(config, workdir)
    lines += [f"  report: {path} ({viewer_note})"]
  return "\n".join(lines)
