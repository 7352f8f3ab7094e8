"""`jaxcal validate FILE`: check a file against the HDF5 contract (CONTRACT.md section 1)."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("file", help="a jaxcal HDF5 file")


def run(args) -> int:
    from jaxcal.commands._common import kind_of, load

    obj = load(args.file)
    print(f"{args.file}: valid jaxcal {kind_of(obj)} file (version 1)")
    return 0
