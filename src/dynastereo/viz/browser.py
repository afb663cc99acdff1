"""Open a page in headless Chromium as a person would, and report what it showed.

Used by the report test and to make the docs' screenshots: Chromium (Debian's
``chromium``) is driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``,
no network port): the page is loaded from its file, and we collect the console's errors
and warnings, uncaught exceptions and failed loads (``Log.entryAdded``), images that did
not decode, the DOM after load and a full-page PNG screenshot.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DynastereoError

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    """The Chromium executable on PATH ($DYNASTEREO_CHROMIUM first), or None."""
    env = os.environ.get("DYNASTEREO_CHROMIUM")
    if env:
        return env if shutil.which(env) else None
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


@dataclass
class PageLoad:
    dom: str  # document.documentElement.outerHTML after the load event
    errors: list[str] = field(default_factory=list)  # console errors, exceptions, failed loads, broken images
    warnings: list[str] = field(default_factory=list)
    screenshot: bytes = b""  # full-page PNG


class _Pipe:
    """The DevTools protocol over Chromium's fds 3 (commands in) / 4 (replies out), NUL-separated JSON."""

    def __init__(self, proc: subprocess.Popen, w: int, r: int, timeout_s: float) -> None:
        self.proc, self.w, self.r, self.timeout_s = proc, w, r, timeout_s
        self.buf = b""
        self.next_id = 0
        self.events: list[dict] = []

    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.r], [], [], left)[0]:
                raise DynastereoError(f"chromium did not answer within {self.timeout_s:g} s")
            chunk = os.read(self.r, 1 << 20)
            if not chunk:
                raise DynastereoError("chromium closed the DevTools pipe (crashed?)")
            self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, session: str | None = None, **params) -> dict:
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout_s
        while True:
            m = self._read_message(deadline)
            if m.get("id") == self.next_id:
                if "error" in m:
                    raise DynastereoError(f"chromium: {method}: {m['error'].get('message')}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, method: str) -> dict:
        for i, m in enumerate(self.events):
            if m.get("method") == method:
                return self.events.pop(i)
        deadline = time.monotonic() + self.timeout_s
        while True:
            m = self._read_message(deadline)
            if m.get("method") == method:
                return m
            self.events.append(m)


def _describe(events: list[dict]) -> tuple[list[str], list[str]]:
    errors, warnings = [], []
    for m in events:
        p = m.get("params", {})
        if m.get("method") == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
            if p.get("type") in ("error", "assert"):
                errors.append(f"console.{p['type']}: {text}")
            elif p.get("type") == "warning":
                warnings.append(f"console.warn: {text}")
        elif m.get("method") == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            errors.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
        elif m.get("method") == "Log.entryAdded":
            e = p.get("entry", {})
            (errors if e.get("level") == "error" else warnings).append(f"{e.get('source')}: {e.get('text')} "
                                                                     f"{e.get('url', '')}".strip())
    return errors, warnings


BROKEN_IMAGES_JS = "[...document.images].filter(i => !i.complete || i.naturalWidth === 0).map(i => i.alt || i.src.slice(0, 60))"


def load_page(path: str | Path, *, width: int = 1200, height: int = 900, screenshot: bool = True,
              timeout_s: float = 60.0, chromium: str | None = None, settle_s: float = 0.0,
              webgl: bool = False) -> PageLoad:
    """Load the HTML file ``path`` (or an ``http://`` URL) in headless Chromium; see
    :class:`PageLoad`.  ``settle_s``: seconds to wait after the load event (a page that
    draws after it, such as the rerun web viewer); ``webgl``: software WebGL (SwiftShader)
    instead of no GPU at all."""
    exe = chromium or find_chromium()
    if exe is None:
        raise DynastereoError("chromium not found (Debian: apt-get install chromium)")
    url = str(path) if str(path).startswith(("http://", "https://")) else Path(path).resolve().as_uri()
    cmd_r, cmd_w = os.pipe()  # we write commands -> chromium reads fd 3
    out_r, out_w = os.pipe()  # chromium writes fd 4 -> we read
    profile = tempfile.mkdtemp(prefix="dynastereo-chromium-")

    def child_fds() -> None:  # in the child, before exec: the pipe ends become fds 3 and 4
        high_r, high_w = fcntl.fcntl(cmd_r, fcntl.F_DUPFD, 10), fcntl.fcntl(out_w, fcntl.F_DUPFD, 10)
        os.dup2(high_r, 3)
        os.dup2(high_w, 4)

    gpu = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"] if webgl else ["--disable-gpu"]
    args = [exe, "--headless", "--remote-debugging-pipe", "--no-sandbox", *gpu, "--no-first-run",
            "--disable-extensions", "--disable-background-networking", f"--user-data-dir={profile}",
            "--hide-scrollbars", "about:blank"]
    proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            preexec_fn=child_fds, pass_fds=(3, 4))
    os.close(cmd_r)
    os.close(out_w)
    pipe = _Pipe(proc, cmd_w, out_r, timeout_s)
    try:
        target = pipe.call("Target.createTarget", url="about:blank")["targetId"]
        s = pipe.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            pipe.call(f"{domain}.enable", s)
        pipe.call("Emulation.setDeviceMetricsOverride", s, width=width, height=height, deviceScaleFactor=1,
                  mobile=False)
        pipe.events.clear()
        pipe.call("Page.navigate", s, url=url)
        pipe.wait_event("Page.loadEventFired")
        if settle_s > 0:
            time.sleep(settle_s)
        dom = pipe.call("Runtime.evaluate", s, expression="document.documentElement.outerHTML",
                        returnByValue=True)["result"]["value"]
        broken = pipe.call("Runtime.evaluate", s, expression=BROKEN_IMAGES_JS, returnByValue=True)["result"]["value"]
        shot = b""
        if screenshot:
            shot = base64.b64decode(pipe.call("Page.captureScreenshot", s, format="png",
                                              captureBeyondViewport=True)["data"])
        errors, warnings = _describe(pipe.events)
        errors += [f"image did not load: {b}" for b in broken]
        try:
            pipe.call("Browser.close")
        except DynastereoError:
            pass
        return PageLoad(dom, errors, warnings, shot)
    finally:
        os.close(cmd_w)
        os.close(out_r)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
