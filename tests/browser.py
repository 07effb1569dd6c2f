"""Headless Chromium for the browser tests: a page loaded at an exact size, then its screenshot with alpha.

Talks the DevTools protocol over `--remote-debugging-pipe` (file descriptors 3 and 4, messages ended by NUL),
so nothing but the standard library is needed. WebGL runs on SwiftShader (ANGLE's CPU backend), the
renderer headless Chromium has where there is no GPU.
"""

from __future__ import annotations

import base64
import io
import json
import os
import select
import shutil
import subprocess
import tempfile
import time

import numpy as np

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-extensions",
    "--mute-audio",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--hide-scrollbars",
]


def chromium_binary() -> str | None:
    """Debian's `chromium` (or a `chromium-browser` / `google-chrome` on the PATH), None when there is none."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


class BrowserError(RuntimeError):
    """The page reported an error, or did not get ready in time; the message carries what the page logged."""


class Chromium:
    """One headless Chromium; `screenshot(url, w, h)` loads a page in a fresh tab and returns RGBA uint8 [h, w, 4]."""

    def __init__(self, binary: str):
        self._profile = tempfile.mkdtemp(prefix="cadsplat-chromium-")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # the protocol's ends are the child's fds 3 (it reads) and 4 (it writes)
            os.dup2(to_child_r, 3)
            os.dup2(from_child_w, 4)

        self._proc = subprocess.Popen(
            [binary, *FLAGS, f"--user-data-dir={self._profile}", "--remote-debugging-pipe", "about:blank"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=fds,
            pass_fds=(3, 4),
        )  # noqa: PLW1509 - it only calls dup2, safe after fork
        os.close(to_child_r)
        os.close(from_child_w)
        self._buffer = b""
        self._next_id = 0
        self.log: list[str] = []

    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_child], [], [], left)[0]:
                raise BrowserError("chromium did not answer in time")
            chunk = os.read(self._from_child, 1 << 20)
            if not chunk:
                raise BrowserError("chromium closed the DevTools pipe")
            self._buffer += chunk
        raw, _, self._buffer = self._buffer.partition(b"\0")
        return json.loads(raw)

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60.0) -> dict:
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})
            self._note(reply)

    def _note(self, event: dict) -> None:
        p = event.get("params", {})
        if event.get("method") == "Runtime.consoleAPICalled":
            self.log.append(
                f"console.{p.get('type')}: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
            )
        elif event.get("method") == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.log.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")

    def screenshot(self, url: str, width: int, height: int, timeout: float = 180.0, probe: str = "null") -> tuple[np.ndarray, object]:
        """RGBA uint8 [height, width, 4] of `url` once it sets `window.cadsplatReady`, over a transparent page, and the
        value of the JavaScript expression `probe` evaluated then."""
        from PIL import Image

        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        try:
            for method in ("Runtime.enable", "Page.enable"):
                self.call(method, session=session)
            self.call(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                session=session,
            )
            self.call("Emulation.setDefaultBackgroundColorOverride", {"color": {"r": 0, "g": 0, "b": 0, "a": 0}}, session=session)
            self.call("Page.navigate", {"url": url}, session=session)
            deadline = time.monotonic() + timeout
            while True:
                state = self.call(
                    "Runtime.evaluate",
                    {"expression": "window.cadsplatReady ? 'ready' : (window.cadsplatError || '')", "returnByValue": True},
                    session=session,
                )["result"].get("value", "")
                if state == "ready":
                    break
                if state or time.monotonic() > deadline:
                    raise BrowserError(f"{url}: {state or 'not ready in time'}; page log: {self.log[-8:]}")
                time.sleep(0.25)
            shot = self.call("Page.captureScreenshot", {"format": "png"}, session=session)["data"]
            value = self.call("Runtime.evaluate", {"expression": probe, "returnByValue": True}, session=session)["result"].get("value")
        finally:
            self.call("Target.closeTarget", {"targetId": target})
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(shot))).convert("RGBA")), value

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10.0)
        except (BrowserError, OSError):
            pass
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for fd in (self._to_child, self._from_child):
            os.close(fd)
        shutil.rmtree(self._profile, ignore_errors=True)


def psnr_over(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) of images a, b [H, W, 3] in [0, 1] over the pixels of mask [H, W]."""
    mse = float(np.mean((a[mask] - b[mask]) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks [H, W]."""
    return float((a & b).sum() / max((a | b).sum(), 1))
