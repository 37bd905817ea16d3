"""bench-ownership's refresh of the marked runs: new runs' trials and rates join the stored ones."""
import json
import sys

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
