#!/usr/bin/env python3
"""Test data and client results of deploy/container-test.sh.

  ct_data.py corrupt SRC DST   copy database SRC to DST with the checksum of
                               every record broken (header intact)
  ct_data.py converged CSV     exit 0 when the last frame of a `planet-view
                               render --reference-db` CSV equals the reference
                               (no coverage mismatch, depth RMSE 0, reference
                               converged)
"""
from __future__ import annotations

import csv
import struct
import sys
from pathlib import Path

SUPERBLOCK_LEN = 64
RECORD_MAGIC = b"PLOD"


def cmd_corrupt(src: str, dst: str) -> int:
    b = bytearray(Path(src).read_bytes())
    if b[:8] != b"PLANETDB":
        print(f"{src}: not a planet database")
        return 1
    header_offset = struct.unpack_from("<Q", b, 16)[0]
    off, n = SUPERBLOCK_LEN, 0
    while off + 8 <= header_offset and b[off:off + 4] == RECORD_MAGIC:
        size = struct.unpack_from("<I", b, off + 4)[0]
        b[off + size - 1] ^= 0xFF  # last byte of the record's CRC-32
        off += size
        n += 1
    if n == 0 or off != header_offset:
        print(f"{src}: record area ends at {off}, header at {header_offset}")
        return 1
    Path(dst).write_bytes(bytes(b))
    print(f"  {dst}: {n} records with a broken checksum")
    return 0


def cmd_converged(path: str) -> int:
    rows = [r for r in csv.DictReader(open(path)) if r["written"] == "1" and r["depth_rmse_m"]]
    if not rows:
        print(f"  {path}: no frame compared with the reference")
        return 1
    last = rows[-1]
    ok = (last["ref_converged"] == "1" and int(last["coverage_mismatch_px"]) == 0
          and float(last["depth_rmse_m"]) == 0.0 and int(last["covered_px"]) > 0)
    print(f"  last frame {last['frame']}: {last['blocks']} blocks, depth RMSE {last['depth_rmse_m']} m, "
          f"coverage mismatch {last['coverage_mismatch_px']} px of {last['covered_px']}, PSNR {last['psnr_db']} dB"
          + ("" if ok else "  FAIL: not equal to the reference"))
    return 0 if ok else 1


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "corrupt":
        return cmd_corrupt(argv[1], argv[2])
    if len(argv) == 2 and argv[0] == "converged":
        return cmd_converged(argv[1])
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
