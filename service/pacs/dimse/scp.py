"""The DICOM node's acceptor side (pynetdicom): C-ECHO and C-STORE SCP with the association policy.

Association policy (checked on A-ASSOCIATE-RQ, in ``EVT_REQUESTED``, answered A-ASSOCIATE-RJ):

* the Called AE Title must be ours (``dicom_ae_title``): rejected-permanent, "called AE title
  not recognised" otherwise;
* the (Calling AE Title, host) pair must be one of ``dicom_peers``: rejected-permanent,
  "calling AE title not recognised" otherwise;
* the data folder must have at least ``min_free_bytes`` free: rejected-transient, "local limit
  exceeded" otherwise (a C-STORE that would go below it answers A700 "out of resources").

C-STORE: the data set is held at most ``max_dicom_instance_bytes`` while it arrives
(:mod:`.receive_bound`), its header checked (:mod:`service.pacs.instance_check`: size as inflated,
pixel dimensions, SOP class, UIDs, truncation; a failure status and nothing kept otherwise); then
it is stored as received (its transfer syntax kept), fsynced, indexed (:mod:`.inbox`), and
answered 0000. An A-RELEASE-RQ commits the association's
instances before the release is confirmed; an instance answered 0000 in an association that
ends otherwise (A-ABORT, a dropped connection, a killed listener) is kept, ``interrupted``, until
the sender comes back (:mod:`.inbox`): a sender retries only what failed. The C-STOREs of a
C-MOVE dsareg asked for (Move Originator AE Title = ours) become ``retrieved`` when their
association ends: the job that asked reads them; they make no job of their own.
"""

from __future__ import annotations

import io
import itertools
import logging
import shutil
import socket
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

from ...storage.interfaces import DicomInbox
from ...storage.records import StoredInstance
from ..instance_check import InstanceLimits, InstanceRefused, check_instance
from .inbox import fsync_file
from .receive_bound import BoundedBuffer, bound_association

log = logging.getLogger("dsareg.dimse")

VERIFICATION = "1.2.840.10008.1.1"
STORAGE_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.12.1": "X-Ray Angiographic Image Storage",
    "1.2.840.10008.5.1.4.1.1.12.1.1": "Enhanced XA Image Storage",
    "1.2.840.10008.5.1.4.1.1.2": "CT Image Storage",
    "1.2.840.10008.5.1.4.1.1.2.1": "Enhanced CT Image Storage",
    "1.2.840.10008.5.1.4.1.1.4": "MR Image Storage",
    "1.2.840.10008.5.1.4.1.1.4.1": "Enhanced MR Image Storage",
    "1.2.840.10008.5.1.4.1.1.13.1.1": "X-Ray 3D Angiographic Image Storage",
    "1.2.840.10008.5.1.4.1.1.66.1": "Spatial Registration Storage (accepted, not used)",
    "1.2.840.10008.5.1.4.1.1.7": "Secondary Capture Image Storage (accepted, not used)",
}
TRANSFER_SYNTAXES = {
    "1.2.840.10008.1.2": "Implicit VR Little Endian",
    "1.2.840.10008.1.2.1": "Explicit VR Little Endian",
    "1.2.840.10008.1.2.1.99": "Deflated Explicit VR Little Endian",
    "1.2.840.10008.1.2.5": "RLE Lossless",
    "1.2.840.10008.1.2.4.70": "JPEG Lossless, first-order prediction (process 14 SV1)",
    "1.2.840.10008.1.2.4.57": "JPEG Lossless (process 14)",
    "1.2.840.10008.1.2.4.50": "JPEG Baseline (process 1)",
    "1.2.840.10008.1.2.4.51": "JPEG Extended (process 2 & 4)",
    "1.2.840.10008.1.2.4.80": "JPEG-LS Lossless",
}
UNCOMPRESSED = ("1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.1.99")

SUCCESS, OUT_OF_RESOURCES, CANNOT_UNDERSTAND = 0x0000, 0xA700, 0xC000
REJECT_CALLING = (0x01, 0x01, 0x03)  # rejected-permanent, service-user, calling AE title not recognised
REJECT_CALLED = (0x01, 0x01, 0x07)  # rejected-permanent, service-user, called AE title not recognised
REJECT_FULL = (0x02, 0x03, 0x02)  # rejected-transient, service-provider (presentation), local limit exceeded
REJECT_LIMIT = REJECT_FULL  # the same code from pynetdicom when its maximum_associations are open


def decodable_transfer_syntaxes() -> list[str]:
    """The accepted transfer syntaxes whose pixel data this installation can decode (pydicom plugins)."""
    from pydicom.pixels import get_decoder

    found = list(UNCOMPRESSED)
    for uid in TRANSFER_SYNTAXES:
        if uid in UNCOMPRESSED:
            continue
        try:
            if get_decoder(uid).is_available:
                found.append(uid)
        except (NotImplementedError, ValueError):
            continue
    return found


def part10_prefix(event: Any) -> bytes:
    """What precedes a received C-STORE data set in a Part 10 file: the 128-byte preamble, ``DICM`` and the file
    meta information pynetdicom made for it."""
    from pynetdicom.dsutils import encode_file_meta

    return b"\x00" * 128 + b"DICM" + encode_file_meta(event.file_meta)


@dataclass(frozen=True)
class Peer:
    ae_title: str
    host: str
    port: int

    @property
    def address(self) -> str:
        try:
            return socket.gethostbyname(self.host)
        except OSError:
            return self.host


def configured_peers(settings: Any) -> dict[str, Peer]:
    """``{AE title: Peer}`` of ``settings.dimse.dicom_peers``."""
    return {p["ae_title"]: Peer(p["ae_title"], p["host"], int(p["port"])) for p in settings.dimse.dicom_peers}


def free_bytes(folder) -> int:
    return shutil.disk_usage(folder).free


class StoreScp:
    """The handlers of one listening AE; ``on_commit(study_uids)`` is told of released associations."""

    def __init__(self, settings: Any, inbox: DicomInbox, blobs: Any, on_commit=None):
        self.settings, self.inbox, self.blobs = settings, inbox, blobs
        self.on_commit = on_commit or (lambda studies: None)
        self.peers = configured_peers(settings)
        self.limits = InstanceLimits.of(settings)
        self.node = uuid.uuid4().hex[:12]
        self._numbers = itertools.count(1)
        self._ids: dict[int, str] = {}
        self._studies: dict[str, set[str]] = {}
        self._closed: dict[int, float] = {}
        self._lock = threading.Lock()
        self.stats = {"associations": 0, "rejected": 0, "stored": 0, "aborted": 0, "refused": 0, "invalid": 0}

    # ---- association policy ---------------------------------------------------------------------
    def policy(self, assoc: Any) -> tuple[int, int, int] | None:
        """The A-ASSOCIATE-RJ (result, source, reason) for this request, or None to go on."""
        request = assoc.requestor.primitive
        calling = str(request.calling_ae_title).strip()
        called = str(request.called_ae_title).strip()
        host = str(assoc.requestor.address)
        if called != self.settings.dimse.dicom_ae_title:
            log.warning("association from %s@%s rejected: called AE title %r is not ours", calling, host, called)
            return REJECT_CALLED
        peer = self.peers.get(calling)
        if peer is None or host not in (peer.address, peer.host):
            log.warning("association from %s@%s rejected: not one of DSAREG_DICOM_PEERS", calling, host)
            return REJECT_CALLING
        if self._disk_low():
            log.error("association from %s rejected: less than %d bytes free in the data folder (DSAREG_MIN_FREE_BYTES)",
                      calling, self.settings.storage.min_free_bytes)
            return REJECT_FULL
        return None

    def _disk_low(self) -> bool:
        floor = self.settings.storage.min_free_bytes
        return bool(floor) and free_bytes(self.settings.storage.data_dir) < floor

    def on_requested(self, event: Any) -> None:
        reason = self.policy(event.assoc)
        if reason is not None:
            self.stats["rejected"] += 1
            event.assoc.acse.send_reject(*reason)
            event.assoc.kill()
            return
        bound_association(event.assoc, self.limits.max_instance_bytes, self.settings.storage.data_dir / "tmp")

    def on_rejected(self, event: Any) -> None:
        """A rejection by the DICOM stack itself, before our policy ran (ours are logged by :meth:`policy`): above all
        the association limit, which a busy modality meets and which left no trace before."""
        assoc = event.assoc
        request, answer = assoc.requestor.primitive, assoc.acceptor.primitive
        calling = str(getattr(request, "calling_ae_title", "") or "").strip()
        reason = (getattr(answer, "result", None), getattr(answer, "result_source", None),
                  getattr(answer, "diagnostic", None))
        self.stats["rejected"] += 1
        if reason == REJECT_LIMIT:
            log.warning("association from %s@%s rejected: the node's %d associations at a time are all open "
                        "(transient: the sender may retry)", calling, assoc.requestor.address,
                        assoc.ae.maximum_associations)
        else:
            log.warning("association from %s@%s rejected by the DICOM stack (result %s, source %s, reason %s)",
                        calling, assoc.requestor.address, *reason)

    def association_id(self, assoc: Any) -> str:
        with self._lock:
            key = id(assoc)
            if key not in self._ids:
                self._ids[key] = f"{self.node}-{next(self._numbers)}"
                self.stats["associations"] += 1
            return self._ids[key]

    # ---- C-STORE ----------------------------------------------------------------------------------
    def on_store(self, event: Any) -> int:
        """Check, store, fsync, index, then answer (0000; A700 too large, out of space or storage failed;
        A900 / C000 an instance that does not check, :mod:`service.pacs.instance_check`)."""
        try:
            return self._store(event)
        finally:
            if isinstance(event.request.DataSet, BoundedBuffer):
                event.request.DataSet.release()  # the spilled file, if any, goes now

    def _store(self, event: Any) -> int:
        if self._disk_low():
            self.stats["refused"] += 1
            return OUT_OF_RESOURCES
        association = self.association_id(event.assoc)
        try:
            checked = self.check(event)
        except InstanceRefused as exc:
            self.stats["invalid"] += 1
            log.warning("C-STORE refused (0x%04X): %s", exc.status, exc.reason)
            return exc.status
        study, series, sop, sop_class = (checked.study_uid, checked.series_uid, checked.sop_instance_uid,
                                         checked.sop_class_uid)
        moved_for = str(getattr(event.request, "MoveOriginatorApplicationEntityTitle", None) or "").strip()
        ours = moved_for == self.settings.dimse.dicom_ae_title
        try:
            digest, size = self.blobs.put_stream(self._part10(event))
            local = self.blobs.local_path(digest)
            if local is not None:
                fsync_file(local)
            calling = str(event.assoc.requestor.ae_title).strip()
            self.inbox.add(StoredInstance(sop, study, series, sop_class, digest, size, calling, time.time()), association,
                           "retrieving" if ours else "received")
        except Exception:
            log.exception("C-STORE of an instance could not be stored")
            return OUT_OF_RESOURCES
        if not ours:
            with self._lock:
                self._studies.setdefault(association, set()).add(study)
        self.stats["stored"] += 1
        return SUCCESS

    def check(self, event: Any):
        """The checked header of the C-STORE's data set (:class:`InstanceRefused` otherwise)."""
        return check_received(event, self.limits)

    @staticmethod
    def _part10(event: Any) -> Any:
        """The instance as a DICOM file (our file meta, then the data set as received), as a stream."""
        buffer = event.request.DataSet
        prefix = part10_prefix(event)
        if isinstance(buffer, BoundedBuffer):
            return buffer.reader(prefix)
        return io.BytesIO(prefix + buffer.getvalue())

    # ---- end of an association ---------------------------------------------------------------------
    # The association's thread reports a release (EVT_RELEASED) or an abort (EVT_ABORTED, also for a
    # connection lost without release); the transport's thread reports the closed connection
    # (EVT_CONN_CLOSE), possibly *before* the release is reported, so a close alone decides nothing:
    # it only starts a grace period after which an association that was neither released nor
    # aborted counts as dead (:meth:`sweep`).
    def on_acse(self, event: Any) -> None:
        """A-RELEASE-RQ received: commit *before* the release is confirmed, so that a peer that saw its
        association end normally never loses an instance (a listener killed right after still has them)."""
        from pynetdicom.pdu_primitives import A_RELEASE

        primitive = event.primitive
        if not isinstance(primitive, A_RELEASE) or primitive.result is not None:
            return
        with self._lock:
            association = self._ids.get(id(event.assoc))
        if association is None:
            return  # nothing stored (an echo)
        try:
            count = self.inbox.commit_association(association)
        except Exception:  # a full disk, a database out: the rows stay open, interrupted by the sweep, kept
            log.exception("association %s: its instances could not be committed (kept, committed later)", association)
            return
        if count:
            log.info("association %s released: %d instance(s) committed", association, count)

    def on_released(self, event: Any) -> None:
        with self._lock:
            association = self._ids.get(id(event.assoc))
            studies = self._studies.pop(association, set()) if association else set()
            self._forget(event.assoc)
        if studies:
            self.on_commit(studies)

    def on_aborted(self, event: Any) -> None:
        """A-ABORT or a connection lost without release: what it stored (answered Success) is kept, interrupted."""
        with self._lock:
            association = self._ids.get(id(event.assoc))
            self._forget(event.assoc)
            self._studies.pop(association, None)
        if association is not None:
            self._interrupt(association)

    def on_closed(self, event: Any) -> None:
        with self._lock:
            if id(event.assoc) in self._ids:
                self._closed[id(event.assoc)] = time.monotonic()

    def _forget(self, assoc: Any) -> None:
        self._ids.pop(id(assoc), None)
        self._closed.pop(id(assoc), None)

    def _interrupt(self, association: str) -> None:
        try:
            kept = self.inbox.interrupt_association(association)
        except Exception:  # the sweep marks them later
            log.exception("association %s ended without release; its instances are marked later", association)
            return
        if kept:
            self.stats["aborted"] += 1
            log.warning("association %s ended without release: %d instance(s) answered Success kept, waiting for "
                        "the sender (at most %g s)", association, kept, self.settings.dimse.dicom_interrupted_wait_seconds)

    def sweep(self, grace_seconds: float = 10.0) -> list[str]:
        """Mark interrupted what associations closed long ago without release or abort (and any dead process) left;
        commit interrupted instances whose sender did not come back in time. The studies that became stable-able."""
        now = time.monotonic()
        with self._lock:
            dead = [key for key, closed in self._closed.items() if now - closed > grace_seconds]
            for key in dead:
                self._closed.pop(key, None)
                self._studies.pop(self._ids.pop(key, ""), None)
            live = set(self._ids.values())
        kept = self.inbox.interrupt_stale(live, older_than_seconds=grace_seconds)
        if kept:
            log.warning("%d instance(s) of associations that ended without release kept, waiting for the sender", kept)
        studies = self.inbox.promote_interrupted(self.settings.dimse.dicom_interrupted_wait_seconds)
        if studies:
            log.warning("%d study(ies) with interrupted instances committed: the sender did not come back within %g s",
                        len(studies), self.settings.dimse.dicom_interrupted_wait_seconds)
        return studies


def check_received(event: Any, limits: InstanceLimits):
    """The checked header of a C-STORE's data set as received (a :class:`BoundedBuffer` or pynetdicom's own
    buffer): :class:`InstanceRefused` past the bound, when it could not be held, or when it does not check."""
    buffer = event.request.DataSet
    if getattr(buffer, "exceeded", False):
        raise InstanceRefused(OUT_OF_RESOURCES, f"more than {limits.max_instance_bytes} bytes received")
    if getattr(buffer, "failed", False):
        raise InstanceRefused(OUT_OF_RESOURCES, "the data set could not be held while it arrived (disk full?)")
    request = event.request
    view = buffer.view() if isinstance(buffer, BoundedBuffer) else buffer.getbuffer()
    return check_instance(view, str(event.context.transfer_syntax),
                          str(request.AffectedSOPClassUID), str(request.AffectedSOPInstanceUID),
                          STORAGE_CLASSES, limits)


def make_ae(settings: Any):
    """The pynetdicom AE of the node: Verification + the storage SOP classes, SCP role."""
    from pynetdicom import AE

    ae = AE(ae_title=settings.dimse.dicom_ae_title)
    ae.maximum_pdu_size = 1 << 20  # 1 MiB P-DATA PDUs (0 = "unlimited" trips dcmtk on encapsulated pixel data)
    for timeout in ("acse_timeout", "dimse_timeout", "network_timeout"):
        setattr(ae, timeout, settings.dimse.dicom_timeout_seconds)
    syntaxes = decodable_transfer_syntaxes()
    ae.add_supported_context(VERIFICATION)
    for sop_class in STORAGE_CLASSES:
        ae.add_supported_context(sop_class, syntaxes)
    return ae


def start_server(settings: Any, scp: StoreScp):
    """Start listening (a thread per association); returns the pynetdicom server (``.shutdown()``)."""
    from pynetdicom import evt

    if not log.isEnabledFor(logging.DEBUG):  # one INFO line per C-STORE otherwise
        logging.getLogger("pynetdicom").setLevel(logging.WARNING)
    ae = make_ae(settings)
    handlers = [(evt.EVT_REQUESTED, scp.on_requested), (evt.EVT_REJECTED, scp.on_rejected),
                (evt.EVT_C_STORE, scp.on_store), (evt.EVT_ACSE_RECV, scp.on_acse),
                (evt.EVT_RELEASED, scp.on_released), (evt.EVT_ABORTED, scp.on_aborted),
                (evt.EVT_CONN_CLOSE, scp.on_closed)]
    return ae.start_server((settings.dimse.dicom_host, settings.dimse.dicom_port), block=False, evt_handlers=handlers)
