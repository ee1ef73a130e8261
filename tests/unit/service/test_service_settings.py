"""Settings: environment, config file, CLI overrides; keys hashed, loopback without keys."""

from __future__ import annotations

import hashlib
import json

from service.storage.blobs import safe_suffix
from service.settings import load_settings


def test_env_file_and_overrides(tmp_path, monkeypatch):
    config = tmp_path / "dsareg.toml"
    config.write_text('workers = 3\nqueue_limit = 7\nretention_hours = 2.5\nhost = "0.0.0.0"\n')
    monkeypatch.setenv("DSAREG_QUEUE_LIMIT", "9")
    monkeypatch.setenv("DSAREG_API_KEYS", "s3cret, other")
    settings = load_settings(config, workers=5, port=None)
    assert settings.workers == 5 and settings.queue_limit == 9 and settings.retention_hours == 2.5
    assert settings.api_keys == [] and settings.api_key_hashes[0] == hashlib.sha256(b"s3cret").hexdigest()
    assert len(settings.api_key_hashes) == 2 and settings.effective_host == "0.0.0.0"
    assert "s3cret" not in json.dumps(settings.model_dump(mode="json"))


def test_no_keys_means_loopback(tmp_path, monkeypatch):
    for name in ("DSAREG_API_KEYS", "DSAREG_API_KEY_HASHES", "DSAREG_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    settings = load_settings(None, host="0.0.0.0", data_dir=tmp_path)
    assert not settings.auth_enabled and settings.effective_host == "127.0.0.1"
    assert settings.effective_database_url.startswith("sqlite:///") and str(tmp_path) in settings.effective_database_url


def test_client_file_names_reduced_to_a_safe_suffix():
    assert safe_suffix("Doe^John_1234.nii.gz") == ".nii.gz"
    assert safe_suffix("../../etc/passwd") == ""
    assert safe_suffix("scan.DCM") == ".dcm"
    assert safe_suffix("patient name.v2.obj") == ".obj"
    assert safe_suffix(None) == ""
