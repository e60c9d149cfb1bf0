"""Helpers of the hostile-input suites about writes, faults and exit codes (tests/test_hostile_*.py).

``run_cli`` runs one command in-process and returns its exit status and stderr; ``snapshot`` hashes a folder
tree (content, mode, link target) so a test can assert that no byte changed outside the allowed outputs.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from pathlib import Path

from fieldcal.cli import main

REPO = Path(__file__).resolve().parents[1]
LENS = REPO / "models" / "triplet-uncorrected.json"
FS = "16"  # cycles/mm: below Nyquist of the 256x144 world
EXIT_CODES = {"ok": 0, "check": 1, "input": 2, "device": 3, "env": 4, "internal": 5, "interrupted": 130}


def run_cli(argv, capsys) -> tuple[int, str]:
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return rc, err


def snapshot(root: Path) -> dict[str, tuple]:
    """relative path -> (kind, sha256 or link target, mode) for everything under ``root``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            st = p.lstat()
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p), 0)
            elif p.is_dir():
                out[rel] = ("dir", "", st.st_mode & 0o777)
            else:
                out[rel] = ("file", hashlib.sha256(p.read_bytes()).hexdigest(), st.st_mode & 0o777)
    return out


def changed(before: dict, after: dict) -> set[str]:
    keys = set(before) | set(after)
    return {k for k in keys if before.get(k) != after.get(k)}


def assert_clean_failure(rc: int, err: str, code: int, *needles: str) -> None:
    """A documented exit status, a one-paragraph what/where/fix message, no traceback."""
    assert rc == code, f"exit {rc}, expected {code}:\n{err}"
    assert "Traceback" not in err and 'File "' not in err, err
    assert "fix:" in err, f"no fix in message:\n{err}"
    low = err.lower()
    for n in needles:
        assert n.lower() in low, f"{n!r} not in message:\n{err}"


def only_under(paths: set[str], allowed: list[str]) -> bool:
    """Every changed relative path lies under one of ``allowed`` (relative paths)."""
    return all(any(p == a or p.startswith(a.rstrip("/") + "/") for a in allowed) for p in paths)


def no_temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp") or ".tmp." in p.name]


# ------------------------------------------------------------------------------------- crafted images


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bomb(width: int, height: int, colour_type: int = 2, bit_depth: int = 8, payload: int = 64) -> bytes:
    """A valid-looking PNG that declares ``width x height`` px with a few bytes of compressed data."""
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b"\0" * payload, 9))
            + _chunk(b"IEND", b""))


def tiff_bomb(width: int, height: int, samples: int = 3, compression: int = 1) -> bytes:
    """A classic little-endian TIFF whose one strip declares ``width x height`` px of uint16 (no real data).

    compression 1 = none (the data would have to be in the file), 8 = deflate (a tiny stream).
    """
    data = zlib.compress(b"\0" * 1024) if compression == 8 else b"\0" * 16
    tags = []

    def tag(code, typ, count, value):
        tags.append((code, typ, count, value))

    header_len = 8
    n_tags = 10
    ifd_len = 2 + n_tags * 12 + 4
    bps_off = header_len + ifd_len
    data_off = bps_off + 2 * samples
    tag(256, 4, 1, width)
    tag(257, 4, 1, height)
    tag(258, 3, samples, bps_off if samples > 2 else 16)
    tag(259, 3, 1, compression)
    tag(262, 3, 1, 2 if samples == 3 else 1)
    tag(273, 4, 1, data_off)
    tag(277, 3, 1, samples)
    tag(278, 4, 1, height)
    tag(279, 4, 1, len(data))
    tag(284, 3, 1, 1)
    out = bytearray(b"II*\x00" + struct.pack("<I", header_len))
    out += struct.pack("<H", n_tags)
    for code, typ, count, value in sorted(tags):
        if typ == 3 and count == 1:
            out += struct.pack("<HHIHH", code, typ, count, value, 0)
        else:
            out += struct.pack("<HHII", code, typ, count, value)
    out += struct.pack("<I", 0)
    out += struct.pack("<" + "H" * samples, *([16] * samples))
    out += data
    return bytes(out)


def set_frame_sha(stack: Path, index: int) -> None:
    """Record the current content hash of frame ``index`` in stack.json (a consistent, crafted stack)."""
    js = stack / "stack.json"
    d = json.loads(js.read_text())
    f = stack / d["frames"][index]["file"]
    d["frames"][index]["sha256"] = hashlib.sha256(f.read_bytes()).hexdigest()
    js.write_text(json.dumps(d, indent=2))
