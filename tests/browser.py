"""Headless Chromium driven over the DevTools protocol (no extra Python package: the
WebSocket client is viser's dependency): open a page, take screenshots. Used by the viewer's
browser test; ``.ci/run`` installs Debian's ``chromium``."""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """``with Browser() as b: b.open(url); png = b.screenshot(until=...)``: one headless
    Chromium page (WebGL by SwiftShader, no GPU). Raises ``RuntimeError`` when Chromium is
    missing or does not start within ``timeout_s``."""

    def __init__(self, size=(900, 700), timeout_s: float = 90.0):
        self.size, self.timeout_s = size, timeout_s

    def __enter__(self) -> "Browser":
        from websockets.sync.client import connect

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("no Chromium found")
        self._profile = tempfile.TemporaryDirectory()
        profile = self._profile.name
        self._proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--disable-quic", "--disable-dev-shm-usage",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             f"--window-size={self.size[0]},{self.size[1]}", f"--user-data-dir={profile}",
             "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port_file = Path(profile) / "DevToolsActivePort"
            deadline = time.monotonic() + self.timeout_s
            while not port_file.exists() or not port_file.read_text().strip():
                if time.monotonic() > deadline or self._proc.poll() is not None:
                    raise RuntimeError("Chromium did not start")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
            ws_url = next(p["webSocketDebuggerUrl"] for p in pages if p.get("type") == "page")
            self._ws = connect(ws_url, max_size=None, open_timeout=10)
            self._next_id = 0
            self.call("Page.enable")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def call(self, method: str, **params) -> dict:
        self._next_id += 1
        self._ws.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=self.timeout_s))
            if msg.get("id") == self._next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def screenshot(self, until=None, every_s: float = 1.0, timeout_s: float | None = None) -> bytes:
        """PNG bytes: screenshots every ``every_s`` until ``until(png)`` holds (or the first,
        without ``until``); the last one when ``timeout_s`` (default the browser's) runs out."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            time.sleep(every_s)
            png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
            if until is None or until(png) or time.monotonic() > deadline:
                return png

    def __exit__(self, *exc) -> None:
        ws = getattr(self, "_ws", None)
        if ws is not None:
            ws.close()
        # Chromium's helper processes (renderer, GPU, crash handler) outlive the main one for a
        # moment and keep writing into the profile: stop the whole process group, then remove it
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(self._proc.pid, sig)
            except ProcessLookupError:  # the group is gone
                pass
            try:
                self._proc.wait(10)
                break
            except subprocess.TimeoutExpired:
                continue
        for _ in range(50):
            try:
                shutil.rmtree(self._profile.name)
                break
            except FileNotFoundError:
                break
            except OSError:  # a helper still finishing a write
                time.sleep(0.1)
        self._profile.cleanup()
