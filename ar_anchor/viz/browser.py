"""Headless Chromium: one page, driven over the DevTools protocol on a pipe (standard library only).

The driver of ``ar-anchor view --screenshot`` (:mod:`.screenshot`) and of the web viewer's browser tests.
Debian's ``chromium`` (``apt install chromium``); WebGL renders on the CPU (SwiftShader). The flags keep a
closed network quiet: no background requests, component updates, sync or first-run pages.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

__all__ = ["CHROMIUM_NAMES", "Browser", "BrowserError", "find_chromium"]

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")  # looked for on PATH
FLAGS = (
    "--headless",
    "--no-sandbox",  # CI runs as root
    "--disable-gpu",
    "--use-angle=swiftshader",  # WebGL on the CPU
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
)


class BrowserError(Exception):
    """Chromium failed or exited, or the page raised: the message says which step, in one line."""


def find_chromium(explicit: str | None = None) -> str | None:
    """The Chromium binary: ``explicit`` (a path or a name on PATH), else the first of :data:`CHROMIUM_NAMES`
    on PATH; None when there is none."""
    for name in [explicit] if explicit else CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


class Browser:
    """One headless page of ``size`` (width, height); :meth:`close` ends Chromium. Its log is ``log_path``;
    ``binary`` the Chromium to start (default: ``chromium`` on PATH), ``profile`` its user data directory (default:
    a new temporary one), ``dark`` the page's preferred colour scheme."""

    def __init__(
        self,
        size: tuple[int, int],
        log_path: Path,
        *,
        binary: str | None = None,
        profile: Path | None = None,
        dark: bool = False,
    ) -> None:
        binary = binary or find_chromium()
        if binary is None:
            raise BrowserError("chromium not found")
        self._own_profile = profile is None  # removed on close
        self._profile = str(profile) if profile is not None else tempfile.mkdtemp(prefix="ar_anchor_chromium_")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def child_fds() -> None:  # the DevTools pipe is fds 3 (commands) and 4 (replies)
            os.dup2(to_chrome_r, 3)
            os.dup2(from_chrome_w, 4)

        width, height = size
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in close()
        self.process = subprocess.Popen(
            [
                binary,
                *FLAGS,
                f"--user-data-dir={self._profile}",
                f"--window-size={width},{height}",
                "--remote-debugging-pipe",
                "about:blank",
            ],
            pass_fds=(3, 4),
            preexec_fn=child_fds,  # noqa: PLW1509 - dup2 only
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=self._log,
        )
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buffer = b""
        self._next_id = 0
        self._session = ""
        try:
            target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
            self._session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            metrics = {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}
            self.send("Emulation.setDeviceMetricsOverride", metrics)
            if dark:
                scheme = {"features": [{"name": "prefers-color-scheme", "value": "dark"}]}
                self.send("Emulation.setEmulatedMedia", scheme)
        except BaseException:
            self.close()
            raise

    def send(self, method: str, params: dict | None = None) -> dict:
        """Call ``method`` (on the page once attached); its result. Events are dropped."""
        self._next_id += 1
        message: dict = {"id": self._next_id, "method": method, "params": params or {}}
        if self._session:
            message["sessionId"] = self._session
        os.write(self._to_chrome, json.dumps(message).encode() + b"\0")
        for reply in self._replies():
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error'].get('message', reply['error'])}")
                return reply.get("result", {})
        raise BrowserError(f"Chromium exited during {method} (exit code {self.process.poll()})")

    def _replies(self) -> Iterator[dict]:
        while True:
            while b"\0" not in self._buffer:
                chunk = os.read(self._from_chrome, 1 << 20)
                if not chunk:
                    return
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            yield json.loads(raw)

    def evaluate(self, expression: str) -> object:
        """The value of a JavaScript ``expression`` in the page (promises awaited)."""
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise BrowserError(f"in the page: {details.get('exception', {}).get('description', details.get('text'))}")
        return result["result"].get("value")

    def navigate(self, url: str) -> None:
        self.send("Page.navigate", {"url": url})

    def screenshot(self) -> np.ndarray:
        """The page as a BGR image."""
        data = base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def close(self) -> None:
        """Close the browser (quietly: it may be gone already)."""
        try:
            self._session = ""
            self.send("Browser.close")
        except (BrowserError, OSError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._to_chrome, self._from_chrome):
            try:
                os.close(fd)
            except OSError:
                pass
        self._log.close()
        if self._own_profile:
            shutil.rmtree(self._profile, ignore_errors=True)
