"""Opening a page in headless Chromium (Debian's `chromium`, `make chromium`) for the tests, through the DevTools
protocol over a pipe: what the page logged as errors and whether its images decoded.

Chromium reads protocol messages from its fd 3 and writes to its fd 4, each a JSON object ended by a NUL byte
(--remote-debugging-pipe), so no port or websocket library is needed.
"""
from __future__ import annotations

import fcntl
import json
import os
import pathlib
import select
import shutil
import subprocess
import tempfile
import time

EXECUTABLE = shutil.which("chromium")
SETTLE_MS = 300
# what the page reports once loaded: each <img> as [decoded, natural width, alt] and the SVG charts' marks
PAGE_STATE = ("JSON.stringify({images: Array.from(document.images, i => [i.complete && i.naturalWidth > 0, "
              "i.naturalWidth, i.alt]), marks: document.querySelectorAll('svg polyline, svg circle').length, "
              "links: Array.from(document.links, a => a.getAttribute('href'))})")


class _Pipe:
  """The DevTools protocol over Chromium's pipe: send a command, wait for its answer, keep every event."""

  def __init__(self, process, to_browser: int, from_browser: int, timeout_s: float):
    self.process, self.to_browser, self.from_browser = process, to_browser, from_browser
    self.deadline, self.buffer, self.events, self.next_id = time.monotonic() + timeout_s, b"", [], 0

  def _message(self) -> dict:
    while b"\0" not in self.buffer:
      left = self.deadline - time.monotonic()
      if left <= 0 or not select.select([self.from_browser], [], [], left)[0]:
        raise TimeoutError("chromium did not answer in time")
      chunk = os.read(self.from_browser, 1 << 16)
      if not chunk:
        raise RuntimeError(f"chromium closed its pipe (exit code {self.process.poll()})")
      self.buffer += chunk
    message, self.buffer = self.buffer.split(b"\0", 1)
    return json.loads(message)

  def call(self, method: str, session: str | None = None, **params) -> dict:
    self.next_id += 1
    message = dict(id=self.next_id, method=method, params=params, **({"sessionId": session} if session else {}))
    os.write(self.to_browser, json.dumps(message).encode() + b"\0")
    while True:
      answer = self._message()
      if answer.get("id") == self.next_id:
        if "error" in answer:
          raise RuntimeError(f"{method}: {answer['error']}")
        return answer["result"]
      self.events.append(answer)

  def wait_for(self, method: str) -> None:
    while not any(event.get("method") == method for event in self.events):
      self.events.append(self._message())


def errors(events: list[dict]) -> list[str]:
  """The page's errors among protocol events: uncaught exceptions, console.error / assert, and the browser's own
  error log entries (a resource that failed to load, a blocked request)."""
  found = []
  for event in events:
    method, params = event.get("method"), event.get("params", {})
    if method == "Runtime.exceptionThrown":
      found.append(json.dumps(params["exceptionDetails"])[:500])
    elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
      found.append(" ".join(str(arg.get("value", arg.get("description", ""))) for arg in params.get("args", [])))
    elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
      found.append(f"{params['entry'].get('text')} {params['entry'].get('url', '')}")
  return found


def _above_4(fd: int) -> int:
  """fd moved to a number above 4 (the old number closed)."""
  moved = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 5)
  os.close(fd)
  return moved


def open_page(path: str | os.PathLike, timeout_s: float = 60.0) -> dict:
  """Loads the file `path` in a fresh headless Chromium, offline; returns {errors: [str], images: [[decoded,
  width, alt]], marks: the SVG polylines and circles, links: [href]}. Network access is refused, so a page
  that fetches anything logs an error."""
  to_read, to_chromium = os.pipe()
  from_chromium, to_write = os.pipe()
  # Chromium's ends above fd 4, so that the redirections onto 3 and 4 never overwrite one with the other; bash (dash
  # reads one-digit fds only) moves them there, not a preexec_fn (no Python may run in a fork of a threaded process)
  to_read, to_write = (_above_4(fd) for fd in (to_read, to_write))
  flags = ["--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe", "--no-first-run",
           "--proxy-server=127.0.0.1:9", "--proxy-bypass-list=<-loopback>"]
  # chromium's helper processes can still write to the profile after the browser exits: its removal may not fail
  with tempfile.TemporaryDirectory(prefix="chromium_profile_", ignore_cleanup_errors=True) as profile:
    process = subprocess.Popen(["bash", "-c", f'exec "$0" "$@" 3<&{to_read} 4>&{to_write}', EXECUTABLE, *flags,
                                f"--user-data-dir={profile}"], pass_fds=(to_read, to_write),
                               stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(to_read)
    os.close(to_write)
    try:
      pipe = _Pipe(process, to_chromium, from_chromium, timeout_s)
      target = pipe.call("Target.createTarget", url="about:blank")["targetId"]
      session = pipe.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
      for domain in ("Runtime", "Log", "Page"):
        pipe.call(f"{domain}.enable", session)
      pipe.call("Page.navigate", session, url=pathlib.Path(path).resolve().as_uri())
      pipe.wait_for("Page.loadEventFired")
      # a moment for what the page logs just after its load event (a failed request's log entry may follow it)
      pipe.call("Runtime.evaluate", session, expression=f"new Promise(done => setTimeout(done, {SETTLE_MS}))",
                awaitPromise=True)
      state = pipe.call("Runtime.evaluate", session, expression=PAGE_STATE, returnByValue=True)["result"]["value"]
      pipe.call("Browser.close")
      return dict(json.loads(state), errors=errors(pipe.events))
    finally:
      os.close(to_chromium)
      os.close(from_chromium)
      if process.poll() is None:
        process.kill()
      process.wait()
