"""A tiny W3C WebDriver client over httpx for Debian's ``chromedriver`` + headless ``chromium``:
enough to open a page, find, type, click, wait and take a screenshot (no Selenium dependency)."""

from __future__ import annotations

import base64
import shutil
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from tests.support.servers import free_port

ELEMENT = "element-6066-11e4-a23f-4a4b9f6f3c6a"


def browser_binaries() -> tuple[str, str]:
    chromium = next((shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None)
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("headless Chromium and chromedriver not installed (Debian: apt-get install chromium "
                    "chromium-driver; .ci/run installs them): the review page test needs a real browser")
    return chromium, driver


class Browser:
    def __init__(self, profile: Path, width: int = 1280, height: int = 1000):
        chromium, driver = browser_binaries()
        self.port = free_port()
        self.log = open(profile.parent / f"chromedriver-{self.port}.log", "wb")  # noqa: SIM115 - closed in close()
        self.process = subprocess.Popen([driver, f"--port={self.port}"], stdout=self.log, stderr=subprocess.STDOUT,
                                        start_new_session=True)
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=60)
        args = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
                "--disable-background-networking", "--disable-component-update", "--disable-default-apps",
                f"--user-data-dir={profile}", "--proxy-server=http://127.0.0.1:9",  # nothing leaves the machine
                f"--window-size={width},{height}", "--force-device-scale-factor=1"]
        caps = {"capabilities": {"alwaysMatch": {"browserName": "chrome",
                                                 "goog:chromeOptions": {"binary": chromium, "args": args}}}}
        deadline = time.monotonic() + 30
        while True:
            try:
                response = self.http.post("/session", json=caps)
                break
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        assert response.status_code == 200, response.text
        self.session = f"/session/{response.json()['value']['sessionId']}"

    def _call(self, method: str, path: str, body: dict | None = None):
        response = self.http.request(method, self.session + path, json=body)
        assert response.status_code == 200, (path, response.text[:500])
        return response.json()["value"]

    def open(self, url: str) -> None:
        self._call("POST", "/url", {"url": url})

    def run(self, script: str, *args):
        return self._call("POST", "/execute/sync", {"script": script, "args": list(args)})

    def find(self, css: str, timeout: float = 20.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            response = self.http.post(self.session + "/elements", json={"using": "css selector", "value": css})
            found = response.json()["value"] if response.status_code == 200 else []
            if found:
                return found[0].get(ELEMENT) or next(iter(found[0].values()))
            if time.monotonic() > deadline:
                raise AssertionError(f"no element '{css}' after {timeout} s")
            time.sleep(0.1)

    def wait(self, script: str, timeout: float = 20.0, what: str = "") -> object:
        deadline = time.monotonic() + timeout
        while True:
            value = self.run(script)
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what or script}")
            time.sleep(0.1)

    def click(self, css: str) -> None:
        self._call("POST", f"/element/{self.find(css)}/click", {})

    def type(self, css: str, text: str) -> None:
        self._call("POST", f"/element/{self.find(css)}/value", {"text": text})

    def keys(self, text: str) -> None:
        """Key presses to the focused element (e.g. "\\ue004" Tab, "\\ue007" Enter)."""
        actions = [a for c in text for a in ({"type": "keyDown", "value": c}, {"type": "keyUp", "value": c})]
        self._call("POST", "/actions", {"actions": [{"type": "key", "id": "keyboard", "actions": actions}]})

    def resize(self, width: int, height: int) -> None:
        """The window's size (headless: the viewport's), e.g. to have a whole page in one screenshot."""
        self._call("POST", "/window/rect", {"width": width, "height": height})

    def screenshot(self, path: Path) -> Path:
        path.write_bytes(base64.b64decode(self._call("GET", "/screenshot")))
        return path

    def element_screenshot(self, css: str, path: Path) -> Path:
        """A PNG of one element as drawn (e.g. a WebGL canvas)."""
        path.write_bytes(base64.b64decode(self._call("GET", f"/element/{self.find(css)}/screenshot")))
        return path

    def close(self) -> None:
        try:
            self.http.delete(self.session)
        except httpx.HTTPError:
            pass
        self.http.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        self.log.close()
