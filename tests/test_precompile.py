"""The install-time compilation (``stereoseed precompile``): the bytecode part."""
from __future__ import annotations

import importlib.util
import struct
from pathlib import Path

import stereoseed
from stereoseed.precompile import compile_bytecode


def test_every_module_gets_current_bytecode_even_where_imports_may_not_write_it(monkeypatch):
    """A container commonly sets PYTHONDONTWRITEBYTECODE: without bytecode beside the sources
    every command would compile the whole package again."""
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")  # a reproducible-build setting: still timestamp-checked files
    package = Path(stereoseed.__file__).resolve().parent
    probe = package / "arrays.py"
    cached = Path(importlib.util.cache_from_source(str(probe)))
    cached.unlink(missing_ok=True)
    assert compile_bytecode()
    for source in sorted(package.rglob("*.py")):
        pyc = Path(importlib.util.cache_from_source(str(source)))
        assert pyc.is_file(), f"no bytecode for {source.name}"
        # the header records the source's modification time: a stale file would be recompiled
        flags, mtime = struct.unpack("<II", pyc.read_bytes()[4:12])
        assert flags == 0 and mtime == int(source.stat().st_mtime) & 0xFFFFFFFF, source.name
