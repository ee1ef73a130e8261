"""Settings: environment, config file, CLI overrides; keys hashed, loopback without keys."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.settings import (GROUP_OF, GROUPS, FlatEnvSource, ServiceSettings, env_name, load_settings,
                              settings_to_env)
from service.storage.blobs import safe_suffix


def test_env_file_and_overrides(tmp_path, monkeypatch):
    config = tmp_path / "dsareg.toml"
    config.write_text('workers = 3\nqueue_limit = 7\nretention_hours = 2.5\nhost = "0.0.0.0"\n')
    monkeypatch.setenv("DSAREG_QUEUE_LIMIT", "9")
    monkeypatch.setenv("DSAREG_API_KEYS", "s3cret, other")
    settings = load_settings(config, workers=5, port=None)
    assert settings.jobs.workers == 5 and settings.limits.queue_limit == 9 and settings.retention.retention_hours == 2.5
    assert settings.auth.api_keys == [] and settings.auth.api_key_hashes[0] == hashlib.sha256(b"s3cret").hexdigest()
    assert len(settings.auth.api_key_hashes) == 2 and settings.effective_host == "0.0.0.0"
    assert "s3cret" not in json.dumps(settings.model_dump(mode="json"))


def test_no_keys_means_loopback(tmp_path, monkeypatch):
    for name in ("DSAREG_API_KEYS", "DSAREG_API_KEY_HASHES", "DSAREG_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    settings = load_settings(None, host="0.0.0.0", data_dir=tmp_path)
    assert not settings.auth.auth_enabled and settings.effective_host == "127.0.0.1"
    assert settings.effective_database_url.startswith("sqlite:///") and str(tmp_path) in settings.effective_database_url


def test_client_file_names_reduced_to_a_safe_suffix():
    assert safe_suffix("Doe^John_1234.nii.gz") == ".nii.gz"
    assert safe_suffix("../../etc/passwd") == ""
    assert safe_suffix("scan.DCM") == ".dcm"
    assert safe_suffix("patient name.v2.obj") == ".obj"
    assert safe_suffix(None) == ""


# ---- grouped settings, flat environment names (issue 25) ----------------------------------------------------
BASE_COMMIT = "ad8dd6e"  # the last flat ServiceSettings
BASE_NAMES_FILE = Path(__file__).parent / "data" / "settings_env_names.txt"
ADDED_SINCE_BASE = {"DSAREG_DICOM_QUERY_PEER", "DSAREG_DICOM_QUERY_RETRY_SECONDS",  # issue 22: the patient's volume
                    # issue 23: PACS exports held for review
                    "DSAREG_EXPORT_AFTER_REVIEW", "DSAREG_EXPORT_MAX_ATTEMPTS", "DSAREG_EXPORT_RETRY_BACKOFF_SECONDS"}
ADDED_SINCE_BASE |= {"DSAREG_MAX_DICOM_INSTANCE_BYTES", "DSAREG_MAX_DICOM_PIXEL_BYTES",  # issue 33: hostile peers
                     "DSAREG_DICOM_INTERRUPTED_WAIT_SECONDS", "DSAREG_PACS_DEADLINE_SECONDS",
                     "DSAREG_HTTP_HEADER_TIMEOUT_SECONDS", "DSAREG_HTTP_BODY_IDLE_TIMEOUT_SECONDS",
                     "DSAREG_HTTP_MAX_CONNECTIONS"}
"""Settings added after the base commit (each a new env name; none of the base's may go or change)."""
ADDED_SINCE_BASE |= {"DSAREG_DICOM_INBOX_RETENTION_HOURS"}  # the DICOM inbox is purged once settled
ADDED_SINCE_BASE |= {"DSAREG_EXPORT_LEASE_SECONDS"}  # issue 34: was a constant (15 s); the tests wait less for it
ADDED_SINCE_BASE |= {"DSAREG_WARM_UP_JOB"}  # issue 34: test servers start without the warm-up job
ADDED_SINCE_BASE |= {"DSAREG_PACS_ACCESS"}  # issue 43: which PACS studies each API key may have fetched
ADDED_SINCE_BASE |= {"DSAREG_MODEL_CACHE_ENTRIES"}  # issue 41: volume models kept for the next job on the volume
ADDED_SINCE_BASE |= {"DSAREG_VALIDATION_VOLUME_MEMORY_MB",  # issue 41: a large volume's allowance at intake
                     "DSAREG_VALIDATION_VOLUME_TIMEOUT_SECONDS"}


def _env_names_of(settings_source: str) -> list[str]:
    """The env names a flat ``ServiceSettings`` module accepts (how ``data/settings_env_names.txt`` was made)."""
    namespace: dict = {"__name__": "base_settings"}
    exec(compile(settings_source, "base_settings.py", "exec"), namespace)  # noqa: S102 - the project's own file
    return sorted(f"DSAREG_{name.upper()}" for name in namespace["ServiceSettings"].model_fields)


def test_the_committed_name_list_is_the_base_commits():
    try:
        source = subprocess.run(["git", "show", f"{BASE_COMMIT}:service/settings.py"], capture_output=True, text=True,
                                check=True, cwd=Path(__file__).parent).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip(f"no git history with {BASE_COMMIT} here (shallow clone); the committed list stands")
    assert BASE_NAMES_FILE.read_text().split() == _env_names_of(source)


def test_the_environment_names_are_those_of_the_flat_settings(monkeypatch):
    base = set(BASE_NAMES_FILE.read_text().split()) | ADDED_SINCE_BASE
    assert {env_name(name) for name in GROUP_OF} == base  # declared
    for name in list(os.environ):
        if name.startswith("DSAREG_"):
            monkeypatch.delenv(name)
    for name in base:
        monkeypatch.setenv(name, "1")
    for group in GROUPS:  # nested forms are not read: the names stay flat
        monkeypatch.setenv(f"DSAREG_{group.upper()}", "{}")
        monkeypatch.setenv(f"DSAREG_{group.upper()}__X", "1")
    read = FlatEnvSource(ServiceSettings)()
    assert {env_name(name) for name in read} == base  # read from the environment, each one


def test_an_env_variable_sets_its_nested_setting(monkeypatch):
    monkeypatch.setenv("DSAREG_DICOMWEB_TIMEOUT_SECONDS", "7.5")
    monkeypatch.setenv("DSAREG_DICOM_PEERS", '[{"ae_title": "PACS", "host": "10.0.0.2", "port": 104}]')
    monkeypatch.setenv("DSAREG_DICOM_JOB_OPTIONS", '{"starts": 2}')
    settings = load_settings(None, workers=2)
    assert settings.dicomweb.dicomweb_timeout_seconds == 7.5 and settings.jobs.workers == 2
    assert settings.dimse.dicom_peers == [{"ae_title": "PACS", "host": "10.0.0.2", "port": 104}]
    assert settings.dimse.dicom_job_options == {"starts": 2}
    again = settings_to_env(settings)  # what a child process gets: flat names, same values
    assert again["DSAREG_DICOMWEB_TIMEOUT_SECONDS"] == "7.5" and "DSAREG_WORKERS" in again
    with pytest.raises(AttributeError, match=r"ServiceSettings\.jobs\.workers"):
        _ = settings.workers  # a branch from before the grouping is told where the setting went


def test_a_bad_value_names_its_env_variable(monkeypatch):
    monkeypatch.setenv("DSAREG_DICOM_PORT", "70000")
    with pytest.raises(ValidationError) as caught:
        load_settings(None)
    assert caught.value.errors()[0]["loc"] == ("DSAREG_DICOM_PORT",)


def test_the_cli_names_the_env_variable_without_a_traceback(tmp_path):
    env = {**os.environ, "DSAREG_LEASE_SECONDS": "soon", "DSAREG_CONFIG": ""}
    done = subprocess.run([sys.executable, "-m", "service", "worker", "--data-dir", str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "DSAREG_LEASE_SECONDS" in done.stderr and "valid number" in done.stderr
    assert "Traceback" not in done.stderr + done.stdout


@pytest.mark.parametrize(("name", "value"), [("DSAREG_DICOM_QUERY_PEER", "PACS2"), ("DSAREG_DICOM_EXPORT", "PACS,PACS2")])
def test_a_query_peer_or_export_destination_must_be_a_peer(monkeypatch, name, value):
    """Named but not in DSAREG_DICOM_PEERS: refused at load (was: every study's lookup or export failed, later)."""
    monkeypatch.setenv("DSAREG_DICOM_PEERS", '[{"ae_title": "PACS", "host": "10.0.0.2", "port": 104}]')
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError, match=f"{name}\\) names 'PACS2', not one of DSAREG_DICOM_PEERS \\(AE titles: PACS\\)"):
        load_settings(None)
    monkeypatch.setenv(name, "PACS")
    assert load_settings(None).dimse.dicom_peers[0]["ae_title"] == "PACS"
