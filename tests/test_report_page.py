"""report.html in a real browser: `wamplan report` writes the page beside report.md; headless Chromium (Debian's
package, installed by scripts/setup.sh) loads it from disk (file://) over the DevTools protocol, logs no console
error, and every video the page links exists and plays (its duration > 0 once its metadata loaded). The videos are
tiny VP9 WebM files written here, named as `wamplan eval` names them; the records are written without episodes."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import time
import urllib.request
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from wamplan.evaluation.records import append_record
from wamplan.evaluation.report import outcome_colors, default_task, write_report

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")
# (condition, seed): outcome; seeds 0 and 1 filmed, 2 not
OUTCOMES = {(1, 0): "aligned_not_descended", (7, 0): "success", (1, 1): "success", (7, 1): "never_lifted",
            (1, 2): "lifted_not_aligned", (7, 2): "success"}


def _webm(path: Path, frames: int = 5, size: int = 32) -> None:
    """A tiny VP9 WebM (``frames`` frames at 10 fps), as eval's videos are encoded."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w", format="webm") as box:
        stream = box.add_stream("libvpx-vp9", rate=10)
        stream.width, stream.height, stream.pix_fmt = size, size, "yuv420p"
        for i in range(frames):
            img = np.full((size, size, 3), 40 * i, np.uint8)  # (S, S, 3)
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                box.mux(packet)
        for packet in stream.encode():
            box.mux(packet)


@pytest.fixture
def run(tmp_path):
    """A finished run of conditions 1 and 7 on seeds 0-2, its report written, and the videos of seeds 0 and 1: each
    episode, condition 7's plan beside the outcome on seed 0, and the pair view of seed 1."""
    run = tmp_path / "run with space"  # links are URL-quoted
    run.mkdir()
    for (c, s), o in OUTCOMES.items():
        append_record(run, dict(condition=c, seed=s, variant="open-loop", success=o == "success", outcome=o,
                                length=150 if o == "success" else 300, chunk_timing_s={}))
    videos = [f"c{c}_seed{s:04d}_{'success' if o == 'success' else 'failure'}.webm"
              for (c, s), o in OUTCOMES.items() if s < 2]
    videos += ["c7_seed0000_success_plan.webm", "pairs/seed0001_c1_vs_c7.webm"]
    for v in videos:
        _webm(run / "videos" / v)
    _webm(run / "videos" / "c7_seed0002_failure.webm")  # a file no record matches (seed 2 succeeded): not linked
    write_report(run)
    return run, {f"videos/{v}" for v in videos}


def test_the_page_links_each_existing_video_from_its_cell(run):
    run, videos = run
    page = (run / "report.html").read_text()
    links = {urllib.request.url2pathname(h) for h in re.findall(r'href="([^"]+\.webm)"', page)}
    assert links == videos and all((run / v).is_file() for v in links)
    assert 'src="figure3.png"' in page and (run / "figure3.png").is_file()
    colors = outcome_colors(default_task())
    for (c, s), o in OUTCOMES.items():  # each cell in its outcome's colour, titled with it
        assert re.search(rf'background:{colors[o]};[^"]*" title="seed {s}, condition {c}: {o.replace("_", " ")},', page)
    assert page.count("<td style=\"background:") == len(OUTCOMES)
    assert "Episode by episode against condition 1" in page and "| 7 |" not in page  # tables drawn, not markdown


class DevTools:
    """One page of a headless Chromium over the DevTools protocol (websockets' sync client): commands, and the
    console errors, uncaught exceptions and failed loads the page reports."""

    def __init__(self, profile: Path) -> None:
        from websockets.sync.client import connect

        self.proc = subprocess.Popen([BROWSER, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                                      "--hide-scrollbars", "--window-size=1200,1600", "--remote-debugging-port=0",
                                      f"--user-data-dir={profile}", "about:blank"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file, deadline = profile / "DevToolsActivePort", time.time() + 10
        while not port_file.is_file() or not port_file.read_text().strip():
            assert time.time() < deadline and self.proc.poll() is None, "Chromium did not open its DevTools port"
            time.sleep(0.05)
        port = port_file.read_text().split()[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
            url = next(t for t in json.load(r) if t["type"] == "page")["webSocketDebuggerUrl"]
        self.held = ExitStack()
        self.ws = self.held.enter_context(connect(url, max_size=None))
        self.next_id, self.errors, self.events = 0, [], []

    def _event(self, msg: dict) -> None:
        self.events.append(msg["method"])
        p = msg.get("params", {})
        if msg["method"] == "Runtime.consoleAPICalled" and p["type"] in ("error", "assert"):
            self.errors.append(" ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
        elif msg["method"] == "Runtime.exceptionThrown":
            self.errors.append(p["exceptionDetails"].get("text"))
        elif msg["method"] == "Log.entryAdded" and p["entry"]["level"] == "error":
            self.errors.append(f"{p['entry']['text']} {p['entry'].get('url', '')}")

    def call(self, method: str, timeout: float = 10, **params) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        deadline = time.time() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.time())))
            if msg.get("id") == self.next_id:
                assert "error" not in msg, msg
                return msg["result"]
            if "method" in msg:
                self._event(msg)

    def wait_for(self, event: str, timeout: float = 10) -> None:
        deadline = time.time() + timeout
        while event not in self.events:
            self._event(json.loads(self.ws.recv(timeout=max(0.01, deadline - time.time()))))

    def close(self) -> None:
        self.held.close()
        self.proc.terminate()
        self.proc.wait(10)


PLAY_EVERY_VIDEO = """Promise.all([...document.querySelectorAll('a[href$=".webm"]')].map(a => new Promise(done => {
  const v = document.createElement('video');
  v.preload = 'metadata'; v.muted = true;
  v.onloadedmetadata = () => done([a.getAttribute('href'), v.duration, v.videoWidth]);
  v.onerror = () => done([a.getAttribute('href'), -1, 0]);
  v.src = a.href;
})))"""


@pytest.mark.skipif(BROWSER is None, reason="chromium is not installed: scripts/setup.sh installs Debian's package "
                                            "(apt-get install chromium)")
def test_chromium_opens_the_page_from_disk_without_errors_and_every_linked_video_plays(run, tmp_path):
    run, videos = run
    browser = DevTools(tmp_path / "profile")
    try:
        for domain in ("Page", "Runtime", "Log"):
            browser.call(f"{domain}.enable")
        browser.call("Page.navigate", url=(run / "report.html").as_uri())
        browser.wait_for("Page.loadEventFired")
        played = browser.call("Runtime.evaluate", expression=PLAY_EVERY_VIDEO, awaitPromise=True,
                              returnByValue=True)["result"]["value"]
        assert {urllib.request.url2pathname(h) for h, _, _ in played} == videos
        assert all(duration > 0 and width == 32 for _, duration, width in played), played  # each loaded and plays
        shown = browser.call("Runtime.evaluate", returnByValue=True, expression=(
            "[document.title, document.querySelectorAll('table.grid td[style]').length, "
            "document.querySelector('img').naturalWidth]"))["result"]["value"]
        assert shown[0].startswith("Evaluation report") and shown[1] == len(OUTCOMES) and shown[2] > 0  # figure drawn
        png = base64.b64decode(browser.call("Page.captureScreenshot", format="png")["data"])
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        browser.call("Runtime.evaluate", expression="console.error('the check sees console errors')")
        assert browser.errors == ["the check sees console errors"], browser.errors  # none but this one
    finally:
        browser.close()
