"""The review page's wording (service/api/ui/static): the pose is labelled as the pose, not as an error among the
metrics, and the API-key box shows only when the server asks for a key (a request answered 401)."""

from __future__ import annotations

import re
from pathlib import Path

STATIC = Path(__file__).resolve().parents[4] / "service" / "api" / "ui" / "static"


def test_the_pose_rows_say_they_are_the_pose_not_an_error():
    app = (STATIC / "app.js").read_text(encoding="utf-8")
    labels = re.findall(r'rows\.push\(\["(Pose [^"]*)"', app)
    assert labels and all("the pose, not an error" in label and "model → C-arm" in label for label in labels), labels


def test_the_key_box_hides_when_a_request_without_a_key_is_not_refused():
    app = (STATIC / "app.js").read_text(encoding="utf-8")
    api = app[app.index("async function api("):]
    api = api[:api.index("\n}\n")]
    assert "showKeyForm(response.status === 401)" in api
    assert 'getElementById("key-form").hidden' in app
    assert ".key[hidden] { display: none; }" in (STATIC / "app.css").read_text(encoding="utf-8")  # .key sets display
