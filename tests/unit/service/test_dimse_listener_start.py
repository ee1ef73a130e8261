"""``DicomListener.start`` imports pydicom and pynetdicom before its dispatcher thread runs.

A listener restarted with a stable study waiting has its dispatcher thread read headers (``import pydicom``)
while the starting thread imports pynetdicom (which imports pydicom): Python breaks that cross-thread import
deadlock by handing one thread a half-initialised ``pydicom.uid``, and the listener died at start (CI, round 8).
The check runs in a fresh interpreter, where neither package has been imported yet."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]

SCRIPT = textwrap.dedent("""
    import sys, threading, types
    import service.pacs.dimse.listener as listener_module
    assert "pydicom" not in sys.modules, "precondition: pydicom not imported yet"
    errors = []

    class Dispatcher:  # reads a waiting study's headers at once, as after a restart
        def start(self):
            def read():
                try:
                    import pydicom
                    pydicom.dcmread
                except Exception as exc:
                    errors.append(repr(exc))
            self.thread = threading.Thread(target=read)
            self.thread.start()

    def start_server(settings, scp):
        try:
            from pynetdicom import AE  # noqa: F401
        except Exception as exc:
            errors.append(repr(exc))

    listener_module.start_server = start_server
    node = listener_module.DicomListener.__new__(listener_module.DicomListener)
    node.settings = types.SimpleNamespace(dimse=types.SimpleNamespace(
        dicom_ae_title="DSAREG", dicom_host="127.0.0.1", dicom_peers=[], dicom_interrupted_wait_seconds=1))
    node.inbox = types.SimpleNamespace(interrupt_stale=lambda live: 0)
    node.dispatcher, node.scp, node.server = Dispatcher(), None, None
    node.start()
    node.dispatcher.thread.join()
    print(errors)
    sys.exit(1 if errors else 0)
""")


def test_a_listener_starting_with_a_study_waiting_imports_pydicom_once_whole():
    for _ in range(3):  # without the eager imports this failed every time on the project's machine
        done = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr[-2000:]
