"""Which callback URLs a server may call, and the signature (service/jobs/callbacks.py)."""

from __future__ import annotations

import hashlib
import hmac

import pytest

from service.jobs.callbacks import backoff_seconds, signature, url_problem, verify
from service.settings import ServiceSettings

ALLOWED = ["https://ris.example.org/hooks/", "http://127.0.0.1:8080/cb"]


@pytest.mark.parametrize("url", [
    "https://ris.example.org/hooks/job-done", "https://ris.example.org:443/hooks/a/b?x=1",
    "https://RIS.example.org/hooks/x", "http://127.0.0.1:8080/cb", "http://127.0.0.1:8080/cb/done",
])
def test_urls_under_an_allowed_prefix(url):
    assert url_problem(url, ALLOWED) is None


@pytest.mark.parametrize("url", [
    "https://ris.example.org/hook", "https://ris.example.org/hooksX/a", "http://ris.example.org/hooks/a",
    "https://ris.example.org:8443/hooks/a", "https://ris.example.org.evil.example/hooks/a",
    "https://evil.example/hooks/", "https://user:pw@ris.example.org/hooks/a", "https://ris.example.org/hooks/../x",
    "https://ris.example.org/hooks/%2E%2E/x", "https://ris.example.org/hooks/a#frag", "http://127.0.0.1:8080/cbx",
    "http://127.0.0.1:8081/cb", "http://127.0.0.1/cb", "https://ris.example.org/hooks/a b", "file:///etc/passwd",
    "https://ris.example.org/hooks/" + "a" * 3000, "http://[::1]:8080/cb", "https://ris.example.org/hooks/a\\..\\b",
])
def test_urls_outside_are_refused_with_a_reason(url):
    assert url_problem(url, ALLOWED)


def test_nothing_is_allowed_without_prefixes():
    assert "not enabled" in url_problem("https://ris.example.org/hooks/a", [])


def test_signature_is_hmac_sha256_hex_of_the_raw_body():
    body = b'{"id":"x","status":"succeeded"}'
    expected = "sha256=" + hmac.new(b"s3cret", body, hashlib.sha256).hexdigest()
    assert signature(body, "s3cret") == expected and verify(body, "s3cret", expected)
    assert not verify(body + b"\n", "s3cret", expected) and not verify(body, "other", expected)
    assert not verify(body, "s3cret", None)


def test_backoff_doubles_and_is_bounded():
    settings = ServiceSettings(callback_retry_backoff_seconds=1.0)
    assert [backoff_seconds(settings, n) for n in (1, 2, 3, 4)] == [1.0, 2.0, 4.0, 8.0]
    assert backoff_seconds(settings, 40) == 300.0


def test_a_secret_is_required_with_allowed_prefixes():
    with pytest.raises(ValueError, match="callback_secret"):
        ServiceSettings(callback_allowed=ALLOWED)
    assert ServiceSettings(callback_allowed=ALLOWED, callback_secret="k").callbacks.callback_allowed == ALLOWED
    listed = ServiceSettings(callback_allowed="https://a.example/x/,https://b.example/", callback_secret="k")
    assert listed.callbacks.callback_allowed == ["https://a.example/x/", "https://b.example/"]
