"""The Python client's ``track``: a later run of one plane sends only that plane's file."""

import httpx
import pytest

from service.cli.client import RegistrationClient


def test_track_sends_only_the_planes_given():
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append((request.url.path, request.read()))
        return httpx.Response(202, json={"id": "new"})

    with RegistrationClient("http://test", transport=httpx.MockTransport(handler)) as client:
        assert client.track("j1", lat=b"LATBYTES")["id"] == "new"
        with pytest.raises(ValueError, match="ap, lat or both"):
            client.track("j1")
    path, body = seen[0]
    assert path == "/v1/registrations/j1/track" and len(seen) == 1
    assert b'name="lat"' in body and b"LATBYTES" in body and b'name="ap"' not in body
