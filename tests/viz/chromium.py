"""Headless Chromium (Debian's `chromium` package) driven over the DevTools protocol on a pipe.

`--remote-debugging-pipe` talks NUL-terminated JSON on file descriptors 3 (commands in) and 4 (replies out): no
debugging port, no websocket client, no Playwright download. The browser runs in its own session so that `close()`
ends it with every helper process it started (zygote, GPU, renderer), whatever state the test is in.

Networking: everything but 127.0.0.1 resolves to nothing (`--host-resolver-rules`), and the background services
(component updates, sync, safe browsing, metrics...) are off: no traffic leaves the machine.
Rendering: no GPU here; WebGL2 runs on SwiftShader through ANGLE (`--use-angle=swiftshader`, and
`--enable-unsafe-swiftshader`, without which Chromium refuses software WebGL).
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import shutil
import signal
import time
from pathlib import Path

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",  # CI and these machines run as root
    "--remote-debugging-pipe",
    # software WebGL2 (the Rerun web viewer needs WebGL2 or WebGPU)
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    # nothing off the machine: no DNS but for 127.0.0.1, no background services
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-domain-reliability",
    "--disable-client-side-phishing-detection",
    "--disable-default-apps",
    "--disable-extensions",
    "--metrics-recording-only",
    "--no-default-browser-check",
    "--no-first-run",
    "--no-pings",
    "--disable-quic",
    "--password-store=basic",
    "--use-mock-keychain",
    "--mute-audio",
    "--hide-scrollbars",
]


def chromium_executable() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


class ChromiumError(RuntimeError):
    pass


class HeadlessChromium:
    """One headless browser with one page; `with HeadlessChromium(...) as browser: browser.open(url)`."""

    def __init__(self, profile_dir: Path, log_path: Path, width: int = 1280, height: int = 800,
                 executable: str | None = None) -> None:
        exe = executable or chromium_executable()
        if exe is None:
            raise ChromiumError("chromium is not installed")
        self.width, self.height = width, height
        args = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile_dir}", f"--window-size={width},{height}",
                "about:blank"]
        cmd_r, cmd_w = os.pipe()  # we write commands, Chromium reads them on fd 3
        res_r, res_w = os.pipe()  # Chromium writes replies on fd 4
        log_fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        null_fd = os.open(os.devnull, os.O_RDONLY)
        # copies above fd 10, so that the dup2s below cannot overwrite a source they still need
        child_in, child_out = (fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (cmd_r, res_w))
        try:
            self.pid = os.posix_spawn(exe, args, dict(os.environ), setsid=True, file_actions=[
                (os.POSIX_SPAWN_DUP2, null_fd, 0), (os.POSIX_SPAWN_DUP2, log_fd, 1),
                (os.POSIX_SPAWN_DUP2, log_fd, 2), (os.POSIX_SPAWN_DUP2, child_in, 3),
                (os.POSIX_SPAWN_DUP2, child_out, 4)])
        finally:
            for fd in (cmd_r, res_w, child_in, child_out, log_fd, null_fd):
                os.close(fd)
        self._w, self._r = cmd_w, res_r
        self._buf = b""
        self._next_id = 0
        self._status: int | None = None
        self.session = ""
        try:
            targets = self.send("Target.getTargets", timeout=30)["targetInfos"]
            page = next(t for t in targets if t["type"] == "page")
            self.session = self.send("Target.attachToTarget", targetId=page["targetId"], flatten=True)["sessionId"]
            self.send("Emulation.setDeviceMetricsOverride", session=self.session, width=width, height=height,
                      deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.close()
            raise

    # -- protocol ---------------------------------------------------------------------------------------------
    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._r], [], [], left)[0]:
                raise ChromiumError("no answer from chromium in time")
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise ChromiumError("chromium closed the DevTools pipe (did it crash? see its log)")
            self._buf += chunk
        message, self._buf = self._buf.split(b"\0", 1)
        return json.loads(message)

    def send(self, method: str, session: str | None = None, timeout: float = 60, **params) -> dict:
        self._next_id += 1
        request = {"id": self._next_id, "method": method, "params": params}
        if session:
            request["sessionId"] = session
        os.write(self._w, json.dumps(request).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            message = self._read_message(deadline)
            if message.get("id") == self._next_id:
                if "error" in message:
                    raise ChromiumError(f"{method}: {message['error']}")
                return message["result"]
            # anything else is an event of a domain nobody enabled here: ignored

    # -- page -------------------------------------------------------------------------------------------------
    def open(self, url: str) -> None:
        result = self.send("Page.navigate", session=self.session, url=url)
        if result.get("errorText"):
            raise ChromiumError(f"cannot open {url}: {result['errorText']}")

    def evaluate(self, expression: str, timeout: float = 30):
        """The JSON value of a JavaScript expression in the page (promises awaited); raises on exceptions."""
        result = self.send("Runtime.evaluate", session=self.session, timeout=timeout, expression=expression,
                           returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise ChromiumError(f"{expression}: {result['exceptionDetails'].get('text')}")
        return result["result"].get("value")

    def screenshot(self, timeout: float = 60) -> bytes:
        """A PNG of the page as it is drawn now."""
        data = self.send("Page.captureScreenshot", session=self.session, timeout=timeout, format="png")["data"]
        return base64.b64decode(data)

    # -- life -------------------------------------------------------------------------------------------------
    def alive(self) -> bool:
        if self._status is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self._status = status
        return self._status is None

    def close(self) -> None:
        """Ends the browser and all its processes (its whole session), then closes the pipes. Idempotent."""
        for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            try:
                os.killpg(self.pid, sig)  # setsid: the group id is the browser's pid
            except ProcessLookupError:
                break
            deadline = time.monotonic() + wait
            while self.alive() and time.monotonic() < deadline:
                time.sleep(0.05)
            if not self.alive():
                # the helpers may outlive the main process by a moment: kill what is left of the group
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.pid, signal.SIGKILL)
                break
        if self.alive():  # pragma: no cover - SIGKILL always ends it
            raise ChromiumError(f"chromium (pid {self.pid}) did not exit")
        for fd in (self._w, self._r):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._w = self._r = -1

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
