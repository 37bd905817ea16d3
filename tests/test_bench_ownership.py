"""bench-ownership's refresh of the marked runs: new runs' trials and rates join the stored ones."""
import json
import sys

import numpy as np

from experiments import bench_ownership


def _rows(owned):
  untouched = dict(kind="none", attack="none", level=None, severity="none", z=9.0, owned=True)
  return [untouched] + [dict(kind="model", attack="noise", level=k, severity="mild", z=5.0 if o else 1.0, owned=o)
                        for k, o in enumerate(owned)]


def test_true_positive_rates_count_only_the_attacked_trials():
  rates = bench_ownership.true_positive_rates({"a": _rows([True, False, True, True]), "b": _rows([True])})
  assert rates == {"a": 0.75, "b": 1.0}


def test_marked_only_merges_the_runs_found_and_keeps_the_rest(tmp_path, monkeypatch):
  stored = dict(clean_trials=100_000, false_positives=0, tpr_at_alpha={"old": 0.5, "lego": 0.0},
                marked={"old": _rows([True, False]), "lego": _rows([False])}, message={})
  (tmp_path / "ownership_bench.json").write_text(json.dumps(stored))
  lego = tmp_path / "lego"
  lego.mkdir()
  for name in ("student.ply", "decoder.msgpack", "key.json", "config.json"):
    (lego / name).write_text("")
  monkeypatch.setattr(bench_ownership, "marked_trials", lambda run, alpha, null_views: _rows([True, True, False, True]))
  monkeypatch.setattr(sys, "argv", ["bench_ownership", f"--out={tmp_path}", "--marked-only",
                                    f"--marked={lego},{tmp_path / 'missing'}"])
  bench_ownership.main()
  result = json.loads((tmp_path / "ownership_bench.json").read_text())
  assert result["tpr_at_alpha"] == {"old": 0.5, "lego": 0.0, str(lego): 0.75}
  assert set(result["marked"]) == {"old", "lego", str(lego)} and result["clean_trials"] == 100_000
  assert (tmp_path / "ownership_tpr.png").is_file()


def test_messages_only_replaces_the_rows_of_the_runs_found(tmp_path, monkeypatch):
  stored = dict(clean_trials=100_000, marked={}, tpr_at_alpha={},
                message={"demo": {"32": dict(run="demo_32", bits=32)}, "lego": {"48": dict(run="lego_48", bits=48)}})
  (tmp_path / "ownership_bench.json").write_text(json.dumps(stored))
  run = tmp_path / "lego_48_10k"
  run.mkdir()
  (run / "message.json").write_text("{}")
  monkeypatch.setattr(bench_ownership, "message_row",
                      lambda run, clean, alpha, scratch: dict(run=str(run), scene="lego", bits=48))
  monkeypatch.setattr(sys, "argv", ["bench_ownership", f"--out={tmp_path}", "--messages-only",
                                    f"--message-runs={tmp_path / 'missing'},{run}"])
  bench_ownership.main()
  message = json.loads((tmp_path / "ownership_bench.json").read_text())["message"]
  assert message == {"demo": {"32": dict(run="demo_32", bits=32)}, "lego": {"48": dict(run=str(run), scene="lego",
                                                                                          bits=48)}}


def test_rates_without_the_owner_copy_skip_runs_that_predate_it():
  aligned = _rows([True, True])
  for row, unaligned in zip(aligned, (True, False, True)):
    row["unaligned"] = dict(owned=unaligned)
  rates = bench_ownership.true_positive_rates({"new": aligned, "old": _rows([True])}, unaligned=True)
  assert rates == {"new": 0.5}


def test_clean_trials_read_against_the_scene_itself_equal_those_without_the_owner_copy():
  """A clean scene whose 'owner's copy' is the scene itself: the tone found at every view is the identity, so the
  trials are those of verify without re-alignment (the per-view path and the batched path agree)."""
  import jax
  from conceal_jax.conceal import reveal, unet
  from conceal_jax.robust import robustness
  from conceal_jax.splat.render import RenderOptions
  from tests.helpers import make_camera, random_gaussians

  scene = random_gaussians(3, 400, degree=1)
  owner = robustness.Owner(decoder=unet.init_decoder(jax.random.key(0), 4, 16), decoder_width=4,
                           hidden=np.random.default_rng(0).uniform(size=(16, 16, 3)).astype(np.float32),
                           check_camera=make_camera(32, 32), options=RenderOptions(background=(1.0, 1.0, 1.0)),
                           reading=reveal.Reading(clip=True))
  cameras = [make_camera(32, 32, eye=(x, -4.0, 1.0)) for x in (-0.5, 0.5)]
  hidden = np.stack([owner.hidden, owner.hidden[::-1]])
  clean = dict(name="clean", gaussians=scene, cameras=cameras)
  plain = bench_ownership.pair_trials(owner, hidden, clean, 1e-3, 4)
  toned = bench_ownership.pair_trials(owner, hidden, clean, 1e-3, 4, marked=scene)
  assert plain["z"].shape == (3, 2)
  np.testing.assert_allclose(toned["z"], plain["z"], atol=1e-4)
  np.testing.assert_array_equal(toned["owned"], plain["owned"])
