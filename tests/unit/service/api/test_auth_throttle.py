"""Wrong API keys throttled per client address (issue 43 item 3): 429 with Retry-After after too many within the
window, in a bounded in-memory map; a WARNING names the address, never the key."""

from __future__ import annotations

import logging

import pytest
from fastapi.testclient import TestClient

from service.api.auth_throttle import FailureThrottle, ThrottlePolicy
from service.app import create_app
from service.settings import load_settings

KEY = "k-throttle-test-valid"
WRONG = "k-throttle-test-WRONG-secret"


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    settings = load_settings(None, data_dir=str(tmp_path_factory.mktemp("data")), api_keys=KEY)
    return create_app(settings, start_background=False)


def test_a_guessing_client_gets_429_with_retry_after_and_is_logged_without_the_key(app, caplog):
    caplog.set_level(logging.INFO)
    with TestClient(app, client=("203.0.113.7", 5000)) as guesser, TestClient(app, client=("198.51.100.2", 5000)) as other:
        wrong = {"Authorization": f"Bearer {WRONG}"}
        codes = [guesser.get("/v1/registrations", headers=wrong).status_code for _ in range(10)]
        blocked = guesser.get("/v1/registrations", headers=wrong)
        valid_too = guesser.get("/v1/registrations", headers={"Authorization": f"Bearer {KEY}"})
        elsewhere = other.get("/v1/registrations", headers={"Authorization": f"Bearer {KEY}"})
    assert codes == [401] * 10
    assert blocked.status_code == 429 and 1 <= int(blocked.headers["retry-after"]) <= 60
    assert blocked.json()["type"].endswith("/too-many-requests") and "retry in" in blocked.json()["detail"]
    assert valid_too.status_code == 429 and elsewhere.status_code == 200  # per client address
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "dsareg.service.auth"]
    assert len(warnings) == 10 and all("203.0.113.7" in w for w in warnings) and "429" in warnings[-1]
    assert not any(WRONG in r.getMessage() or KEY in r.getMessage() for r in caplog.records)


def test_the_window_slides_and_the_map_is_bounded():
    now = [0.0]
    throttle = FailureThrottle(ThrottlePolicy(max_failures=3, window_s=10, max_clients=100), clock=lambda: now[0])
    for _ in range(3):
        throttle.failed("a")
    assert throttle.retry_after("a") == 10 and throttle.retry_after("b") is None
    now[0] = 9.2
    assert throttle.retry_after("a") == 1
    now[0] = 10.5
    assert throttle.retry_after("a") is None  # the oldest failure left the window
    throttle.failed("a")
    assert throttle.retry_after("a") is None  # two of the last three are within 10 s
    throttle.forget("a")
    for n in range(1000):
        throttle.failed(f"10.0.{n // 256}.{n % 256}")
    assert len(throttle) == 100 and throttle.retry_after("a") is None
