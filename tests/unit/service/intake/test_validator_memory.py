"""The validator's per-parse address-space allowance is measured from the process's size at each request.

A fixed limit set once at start-up let what earlier parses left mapped (thread arenas, lazily loaded libraries)
eat the allowance of later ones: on a long-lived server a small CTA read was refused as a memory bomb after
many parses (round 9). Run in a fresh interpreter, since RLIMIT_AS cannot be lifted again."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[4]

SCRIPT = textwrap.dedent("""
    import mmap
    from service.intake.validator_process import _address_space_bytes, _allow_next_parse, _grown_too_much
    MiB = 1024 * 1024

    def mapped(mib):
        block = mmap.mmap(-1, mib * MiB)
        return block

    start = _address_space_bytes()
    _allow_next_parse(96)
    kept = [mapped(64)]                        # a parse that leaves 64 MiB mapped: within its 96 MiB
    try:
        mapped(64)                             # 128 MiB in one parse: over the allowance
        raise SystemExit("a parse past its allowance was not stopped")
    except (MemoryError, OSError):
        pass
    _allow_next_parse(96)                      # the next request: 96 MiB on top of what is mapped now
    kept.append(mapped(64))                    # refused by a limit fixed at start-up (64 + 64 > 96)
    assert _grown_too_much(start, 96), "a process that kept more than one allowance is to be recycled"
    assert not _grown_too_much(start, 512)
    print("ok")
""")


def test_each_parse_gets_its_whole_allowance_and_a_grown_process_is_recycled():
    done = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stdout + done.stderr[-2000:]
