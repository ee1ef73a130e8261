"""``dsareg submit --mesh-units`` sends the unit as ``options.mesh_units`` (a loopback HTTP server records the post)."""

from __future__ import annotations

import json
import threading
from email.parser import BytesParser
from email.policy import default
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from dsareg_engine.cli import main

PHANTOM = Path(__file__).resolve().parents[3] / "examples" / "phantom"


class _Recorder(BaseHTTPRequestHandler):
    posts: list[tuple[str, bytes, str]] = []

    def do_POST(self):  # noqa: N802 - http.server's name
        body = self.rfile.read(int(self.headers["Content-Length"]))
        self.posts.append((self.path, body, self.headers["Content-Type"]))
        reply = json.dumps({"id": "job-1", "status": "queued", "links": {"self": "/v1/registrations/job-1"}}).encode()
        self.send_response(202)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(reply)))
        self.end_headers()
        self.wfile.write(reply)

    def log_message(self, *args):
        pass


@pytest.fixture()
def recorder():
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Recorder)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    _Recorder.posts = []
    yield f"http://127.0.0.1:{server.server_port}", _Recorder.posts
    server.shutdown()
    server.server_close()


def _form_fields(body: bytes, content_type: str) -> dict[str, bytes]:
    message = BytesParser(policy=default).parsebytes(f"Content-Type: {content_type}\r\n\r\n".encode() + body)
    return {part.get_param("name", header="content-disposition"): part.get_payload(decode=True)
            for part in message.iter_parts()}


def test_submit_sends_mesh_units_in_the_options(recorder, capsys):
    url, posts = recorder
    code = main(["submit", "--server", url, "--mesh", str(PHANTOM / "mesh.ply"), "--ap", str(PHANTOM / "ap.png"),
                 "--lat", str(PHANTOM / "lat.png"), "--geometry", "paper", "--options", '{"starts": 2}',
                 "--mesh-units", "cm"])
    assert code == 0 and capsys.readouterr().out.strip() == "job-1"
    (path, body, content_type), = posts
    assert path == "/v1/registrations"
    options = json.loads(_form_fields(body, content_type)["options"])
    assert options == {"starts": 2, "mesh_units": "cm"}


def test_an_unknown_unit_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        main(["submit", "--server", "http://127.0.0.1:9", "--mesh", str(PHANTOM / "mesh.ply"), "--ap",
              str(PHANTOM / "ap.png"), "--lat", str(PHANTOM / "lat.png"), "--mesh-units", "inch"])
    assert info.value.code == 2 and "mm" in capsys.readouterr().err
