"""``dsareg phantom-study``: write a synthetic DICOM study to send to a PACS (a test of the path, no patient data)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "phantom-study", help="write a synthetic DICOM study (native XA runs + a CT series) to send to a PACS",
        description="Write one DICOM study of an obviously synthetic patient (PHANTOM^DSAREG): the AP and LAT "
                    "native XA runs of a biplane C-arm (multi-frame, mask frames before the contrast, a "
                    "subtraction recipe) and a CT angiography series of the same vessel tree. Send it with "
                    "dcmtk's storescu (the command is printed), then register it from the PACS. truth.json holds "
                    "the pose a registration should return.")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder to write into (created if missing)")
    parser.add_argument("--size-px", type=int, default=512, metavar="N",
                        help="side of the XA images in pixels, 128 to 2048 (default 512)")
    parser.add_argument("--seed", type=int, default=3, metavar="N", help="which phantom (default 3)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import DsaregInputError
    from ..simulation.native_study import make_native_study, write_study

    if not 128 <= args.size_px <= 2048:
        raise DsaregInputError(f"{args.size_px} px is out of range", field="--size-px", accepted="128 to 2048")
    out = Path(args.out)
    study = make_native_study(seed=args.seed, size_px=args.size_px)
    written = write_study(study, out)
    size_mb = sum(path.stat().st_size for path in written) / 1e6
    print(f"wrote {len(written)} DICOM instances ({size_mb:.1f} MB) of study {study.study_uid} under {out}:")
    print(f"  {out / 'XA'}: AP and LAT native runs (series 1, 2); {out / 'CT'}: CT angiography (series 3)")
    print(f"  {out / 'truth.json'}: the pose a registration should return (not DICOM)")
    print("send it to a PACS (its AE title, host and DICOM port):")
    print(f"  storescu -aec PACS_AE_TITLE pacs.example 4242 +sd +r {out / 'XA'} {out / 'CT'}")
    print("or register it here:")
    print(f"  dsareg register --volume {out / 'CT'} --ap {out / 'XA' / 'AP.dcm'} --lat {out / 'XA' / 'LAT.dcm'} "
          f"--ground-truth {out / 'truth.json'} --out {out / 'result'}")
    return 0
