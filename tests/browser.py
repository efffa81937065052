"""Headless Chromium driven over the DevTools protocol on a pipe (import as ``from browser import ...``).

Why the DevTools protocol on ``--remote-debugging-pipe``: it needs nothing beyond the
standard library (no websocket client, no Playwright with its own Node.js driver and
browser build), it is Chromium's stable automation interface, and it reports every
console message, uncaught exception and log entry as a structured event, where
``--enable-logging=stderr`` prints them in a free-text log format that changes between
releases (and that new headless mode does not always write). Messages are JSON objects,
each terminated by a NUL byte, read from fd 3 and written to fd 4 of the browser.

The browser is started with a fresh profile and no network, sync, component updates or
first-run pages, so a test never reaches outside the machine.
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
from typing import Any

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-default-apps", "--disable-extensions", "--mute-audio", "--hide-scrollbars",
         "--remote-debugging-pipe")


def find_chromium() -> str | None:
    """The path of a Chromium executable (``$PHOTONPANO_CHROMIUM`` first, then the PATH), or None."""
    given = os.environ.get("PHOTONPANO_CHROMIUM")
    if given:
        return given if Path(given).is_file() else None
    for name in CHROMIUM_CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


def _high_fd(fd: int) -> int:
    """A copy of ``fd`` numbered 10 or more (the original is closed)."""
    high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return high


@dataclass
class PageLoad:
    """What a page did while it loaded and ran.

    Attributes:
        errors: one line per console message of level error/assert, uncaught exception
            or browser log entry of level error (failed resource, blocked request).
        console: every console message as ``"type: text"``.
        events: every raw DevTools event received (``{"method": ..., "params": ...}``).
    """

    errors: list[str] = field(default_factory=list)
    console: list[str] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)


class Chromium:
    """One headless Chromium process with one page, driven over the DevTools pipe.

    Use as a context manager; the browser and its temporary profile are removed on exit.

    Args:
        executable: the browser (see :func:`find_chromium`).
        width: viewport width in CSS pixels (device scale factor 1).
        height: viewport height in CSS pixels.
        timeout_s: seconds to wait for any one reply or the page load.

    Raises:
        RuntimeError: the browser exits or does not answer within ``timeout_s``.
    """

    def __init__(self, executable: str, width: int = 1200, height: int = 900, timeout_s: float = 60.0) -> None:
        self.executable, self.width, self.height, self.timeout_s = executable, width, height, timeout_s
        self.load = PageLoad()
        self._next_id = 0
        self._buffer = b""
        self._session = ""

    def __enter__(self) -> Chromium:
        self._profile = tempfile.mkdtemp(prefix="photonpano-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # numbered above 9 so that moving them to 3 and 4 in the child cannot close one another
        to_browser_r, from_browser_w = (_high_fd(to_browser_r), _high_fd(from_browser_w))
        args = [*FLAGS, f"--user-data-dir={self._profile}", f"--window-size={self.width},{self.height}",
                "about:blank"]
        # the browser reads commands on fd 3 and writes replies on fd 4
        script = f'exec "$0" "$@" 3<&{to_browser_r} 4>&{from_browser_w} {to_browser_r}<&- {from_browser_w}>&-'
        self._process = subprocess.Popen(["/bin/bash", "-c", script, self.executable, *args],
                                         pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        os.close(to_browser_r)
        os.close(from_browser_w)
        try:
            target = self.send("Target.createTarget", url="about:blank")["targetId"]
            self._session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            for domain in ("Page", "Runtime", "Log"):
                self.send(f"{domain}.enable")
            self.send("Emulation.setDeviceMetricsOverride", width=self.width, height=self.height,
                      deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            os.close(self._to_browser)
        except OSError:
            pass
        try:
            self._process.terminate()
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        finally:
            if self._process.stderr is not None:
                self._process.stderr.close()
            os.close(self._from_browser)
            shutil.rmtree(self._profile, ignore_errors=True)

    # -- protocol --------------------------------------------------------------------
    def send(self, method: str, **params: Any) -> dict[str, Any]:
        """Send one DevTools command (to the page once attached) and return its result.

        Raises:
            RuntimeError: the command failed, or no reply within the timeout.
        """
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if self._session:
            message["sessionId"] = self._session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        reply = self._wait(lambda m: m.get("id") == self._next_id, method)
        if "error" in reply:
            raise RuntimeError(f"chromium: {method} failed: {reply['error']}")
        return reply.get("result", {})

    def _wait(self, done: Any, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + self.timeout_s
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                message = json.loads(raw)
                if "method" in message:
                    self._record(message)
                if done(message):
                    return message
            left = deadline - time.monotonic()
            ready = select.select([self._from_browser], [], [], max(left, 0))[0] if left > 0 else []
            chunk = os.read(self._from_browser, 1 << 20) if ready else b""
            if not chunk:
                state = "timed out" if not ready else "closed the pipe"
                self._process.kill()
                stderr = self._process.communicate()[1].decode(errors="replace")[-2000:]
                raise RuntimeError(f"chromium {state} waiting for {what}; stderr: {stderr}")
            self._buffer += chunk

    def _record(self, event: dict[str, Any]) -> None:
        self.load.events.append(event)
        method, params = event["method"], event.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
            self.load.console.append(f"{params['type']}: {text}")
            if params["type"] in ("error", "assert"):
                self.load.errors.append(f"console.{params['type']}: {text}")
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            text = details.get("exception", {}).get("description") or details.get("text", "")
            self.load.errors.append(f"uncaught exception: {text}")
        elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
            entry = params["entry"]
            self.load.errors.append(f"log ({entry.get('source')}): {entry.get('text')} {entry.get('url', '')}")

    # -- page ------------------------------------------------------------------------
    def open(self, path: Path) -> PageLoad:
        """Load a local file and wait for its load event; returns what the page reported so far."""
        self.load = PageLoad()
        self.send("Page.navigate", url=Path(path).resolve().as_uri())
        self._wait(lambda m: m.get("method") == "Page.loadEventFired", f"the load event of {path}")
        self.evaluate("1")  # let scripts queued by the load event run and report
        return self.load

    def evaluate(self, expression: str) -> Any:
        """The JSON value of a JavaScript expression in the page (promises awaited).

        Raises:
            RuntimeError: the expression threw.
        """
        result = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"chromium: {expression!r} threw {result['exceptionDetails']}")
        return result["result"].get("value")

    def screenshot(self, clip: dict[str, float] | None = None) -> bytes:
        """PNG bytes of the page: the viewport, or ``clip`` (``x, y, width, height`` in CSS pixels of the page)."""
        params: dict[str, Any] = {"format": "png", "captureBeyondViewport": clip is not None}
        if clip is not None:
            params["clip"] = {**clip, "scale": 1}
        return base64.b64decode(self.send("Page.captureScreenshot", **params)["data"])
