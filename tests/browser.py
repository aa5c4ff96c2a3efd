"""Headless Chromium (Debian's ``chromium`` package) driven over the DevTools protocol, for browser checks.

One page: :meth:`Browser.open` a URL, :meth:`Browser.wait_for` a JavaScript condition on it (the page
renders after its own requests: a fixed delay would be too short on a busy machine or too long on an idle
one), read it with :meth:`Browser.evaluate`, save :meth:`Browser.screenshot`. The browser runs as a
process of :mod:`tests.procs` (its own group, stopped by :meth:`Browser.close`) with a fresh profile and
without the background connections that a machine without network refuses.
"""
from __future__ import annotations

import base64
import json
import shutil
import time
import urllib.request
from pathlib import Path
from typing import Any

from tests import procs

#: Chromium's switches for a machine without network or display (tests/README.md, "Shared pieces")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars", "--remote-debugging-port=0"]


def chromium() -> str | None:
    """The Chromium executable on ``PATH`` (Debian's ``chromium``), or ``None``."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


class Browser:
    def __init__(self, folder: Path, width: int = 1600, height: int = 1000, timeout: float = 60.0):
        from websockets.sync.client import connect

        exe = chromium()
        if exe is None:
            raise FileNotFoundError("chromium is not installed (apt-get install chromium)")
        profile = folder / "chromium-profile"
        profile.mkdir(parents=True, exist_ok=True)
        (profile / "DevToolsActivePort").unlink(missing_ok=True)   # a previous browser's port
        self.log = folder / "chromium.log"
        self.proc = procs.start([exe, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                                 "about:blank"], procs.child_env(), self.log)
        self._id = 0
        try:
            port = self._devtools_port(profile / "DevToolsActivePort", timeout)
            pages = self._targets(port, timeout)
            self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout)
            self.send("Page.enable")
            self.send("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)
        except BaseException:
            procs.stop(self.proc)
            raise

    def _devtools_port(self, path: Path, timeout: float) -> int:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited with {self.proc.returncode}:\n{procs.tail(self.log)}")
            if path.exists() and path.read_text().strip():
                return int(path.read_text().split()[0])
            time.sleep(0.2)
        raise TimeoutError(f"chromium wrote no DevTools port within {timeout:.0f} s:\n{procs.tail(self.log)}")

    @staticmethod
    def _targets(port: int, timeout: float) -> list[dict]:
        end = time.monotonic() + timeout
        while True:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages or time.monotonic() > end:
                return pages
            time.sleep(0.2)

    def send(self, method: str, timeout: float = 60.0, **params: Any) -> dict:
        """Call a DevTools method and return its result (events that arrive meanwhile are dropped)."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(end - time.monotonic(), 0.01)))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.send("Page.navigate", url=url)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-serializable values)."""
        result = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:80]}: {result['exceptionDetails'].get('text')}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float) -> Any:
        """Poll a JavaScript expression until it is truthy (an exception counts as not yet: the page may be
        between documents); its value, or ``TimeoutError`` with the page's address and text."""
        end = time.monotonic() + timeout
        error = ""
        while True:
            try:
                value = self.evaluate(expression)
            except RuntimeError as err:
                value, error = None, str(err)
            if value:
                return value
            if time.monotonic() > end:
                text = self.evaluate("document.body ? document.body.innerText : ''") or ""
                raise TimeoutError(f"not true within {timeout:.0f} s: {expression} {error}\n"
                                   f"at {self.evaluate('location.href')}, page text:\n{text[:3000]}")
            time.sleep(0.5)

    def screenshot(self, path: Path) -> Path:
        data = self.send("Page.captureScreenshot", format="png")["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            procs.stop(self.proc)
