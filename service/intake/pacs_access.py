"""Which PACS studies an API key may have fetched by reference (DICOMweb URL or DIMSE peer and a study UID).

A job by reference makes the server read a study from a PACS it holds credentials for, and the job then shows
that study's patient (``case``). With API keys on, a key may therefore pull only what its policy grants
(``DSAREG_PACS_ACCESS``, the ``auth`` group of the settings): a JSON object from a key's SHA-256 digest (64 hex
characters, or at least its first 16, as ``dsareg jobs owners`` and the logs show ``key:<16 hex>``), or ``"*"``
for every key without its own entry, to a policy::

    {"<sha256 hex>": {"peers": ["https://pacs.example/dicom-web", "ORTHANC"],
                      "studies": ["1.2.826.0.1.3680043.8.498."]},
     "*": {"peers": []}}

``peers``: DICOMweb base URLs (of ``DSAREG_DICOMWEB_SERVERS``) and DIMSE AE titles (of ``DSAREG_DICOM_PEERS``)
the key may pull from, or ``["*"]`` for every configured one. ``studies`` (optional; absent: any study of those
peers): Study Instance UIDs, or UID roots ending in ``.`` that a study's UID must start with. **A key without an
entry, and without a ``"*"`` entry, may pull nothing** (403): granting is explicit. Without API keys (a server on
127.0.0.1 only) there is no policy. Uploads and studies received by the DICOM node are not concerned: the
client or the PACS sent them.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any

from .refusals import Refusal

EVERY_KEY = "*"
_HEX = re.compile(r"[0-9a-f]{16,64}")
ACCEPTED = ('a JSON object {"<API key SHA-256 hex, >= 16 characters>" or "*": {"peers": [DICOMweb URL or DIMSE AE '
            'title, or "*"], "studies": [Study Instance UID, or UID root ending in "."] (optional)}}')


class AccessDenied(Refusal):
    """The caller's key may not have this study fetched (answered 403; the study's existence is not told)."""

    default_kind = "forbidden"


@dataclass(frozen=True)
class PacsPolicy:
    """What one key may pull: ``peers`` (None: every configured one) and ``studies`` (empty: any study)."""

    peers: frozenset[str] | None
    studies: tuple[str, ...] = ()

    def allows_peer(self, peer: str) -> bool:
        return self.peers is None or _peer(peer) in self.peers

    def allows_study(self, study_uid: str) -> bool:
        return not self.studies or any(study_uid == s or (s.endswith(".") and study_uid.startswith(s))
                                       for s in self.studies)


def _peer(text: str) -> str:
    """A peer as compared: a DICOMweb URL as the server normalises it (no trailing ``/``), an AE title stripped."""
    return text.strip().rstrip("/")


def _strings(value: Any, where: str) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(item, str) and item.strip() for item in value):
        raise ValueError(f"{where} must be a list of non-empty strings; accepted: {ACCEPTED}")
    return [item.strip() for item in value]


def _policy(value: dict[str, list[str]]) -> PacsPolicy:
    peers = value["peers"]
    return PacsPolicy(None if EVERY_KEY in peers else frozenset(_peer(p) for p in peers), tuple(value["studies"]))


def parse_pacs_access(value: Any) -> dict[str, dict[str, list[str]]]:
    """The setting (JSON text, or a mapping from a config file) checked and normalised: ``{key digest (lower case)
    or "*": {"peers": [...], "studies": [...]}}`` (plain JSON, as settings are dumped and passed on).

    Raises:
        ValueError: naming the entry at fault and what is accepted.
    """
    if isinstance(value, str):
        if not value.strip():
            return {}
        try:
            value = json.loads(value)
        except ValueError:
            raise ValueError(f"pacs_access is not valid JSON; accepted: {ACCEPTED}") from None
    if not isinstance(value, dict):
        raise ValueError(f"pacs_access must be a JSON object; accepted: {ACCEPTED}")
    checked = {}
    for key, policy in value.items():
        name = str(key).strip().lower()
        if name != EVERY_KEY and not _HEX.fullmatch(name):
            raise ValueError(f"pacs_access key {str(key)[:20]!r} is not an API key's SHA-256 hex digest (at least "
                             f"16 hex characters) or '*'; accepted: {ACCEPTED}")
        where = f"pacs_access[{str(key)[:20]!r}]"
        if not isinstance(policy, dict) or "peers" not in policy or set(policy) - {"peers", "studies"}:
            raise ValueError(f"{where} must be an object with 'peers' (and optionally 'studies'); "
                             f"accepted: {ACCEPTED}")
        checked[name] = {"peers": _strings(policy["peers"], f"{where}.peers"),
                         "studies": _strings(policy.get("studies", []), f"{where}.studies")}
    return checked


def policy_of(policies: dict[str, dict[str, list[str]]], who: str) -> PacsPolicy | None:
    """The policy of the caller ``who`` (``key:<16 hex>``): its own entry, else the ``"*"`` one, else None."""
    prefix = who.removeprefix("key:")
    own = [policy for name, policy in policies.items() if name != EVERY_KEY and name[:16] == prefix[:16]]
    chosen = own[0] if own else policies.get(EVERY_KEY)
    return None if chosen is None else _policy(chosen)


def check_access(policies: dict[str, dict[str, list[str]]], who: str, *, peer: str, peer_field: str, study_uid: str,
                 study_field: str) -> None:
    """Raise :class:`AccessDenied` unless ``who``'s policy grants ``peer`` and ``study_uid`` (keys on only)."""
    policy = policy_of(policies, who)
    if policy is None:
        raise AccessDenied("this API key may not fetch studies from a PACS on this server (the administrator "
                           "grants it in DSAREG_PACS_ACCESS)", field=peer_field, accepted="an upload of the files")
    if not policy.allows_peer(peer):
        raise AccessDenied("this API key may not fetch studies from this PACS (DSAREG_PACS_ACCESS)",
                           field=peer_field)
    if not policy.allows_study(study_uid):
        raise AccessDenied("this API key may not fetch this study (DSAREG_PACS_ACCESS)", field=study_field)
