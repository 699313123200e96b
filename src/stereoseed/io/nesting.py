"""How deeply a small structured text file (JSON, OpenCV's FileStorage YAML or XML) nests, measured
before any parser sees it: the parsers recurse once per level, and a file of ``[`` x 100000 makes
Python's json raise RecursionError and OpenCV's FileStorage crash the process (SIGSEGV), both far
below the sizes a file may have. :func:`read_bounded_text` reads such a file whole, refusing one
too large or nested too deep, in one line naming it.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError

__all__ = ["MAX_NESTING", "MAX_SMALL_FILE_BYTES", "nesting_depth", "read_bounded_text"]

# our files nest 5 levels at most (target.json: faces, a face, its board, an axis), OpenCV's
# calibration files 3 (opencv_storage, camera_matrix, data); Python's json gives up near 1000 and
# OpenCV's parser crashes some thousands deep: 64 leaves room for any real file and stays far below
MAX_NESTING = 64
# a calibration or target file is a few kilobytes (one with every view's pose some hundred): a
# larger one is not one, and is not read whole into memory to find that out
MAX_SMALL_FILE_BYTES = 4 * 2**20

_QUOTED = re.compile(r'"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'')  # a string's brackets do not nest
_DASHES = re.compile(r"^[ \t]*((?:-[ \t]+)+)", re.MULTILINE)  # YAML's "- - - x": one sequence in another per dash
_TAG = re.compile(r"<(/?)[A-Za-z_][^<>]*?(/?)>")  # an XML element's start or end (not <?...?>, <!-- -->)


def nesting_depth(text: str) -> int:
    """An upper bound of how deeply ``text`` nests: its brackets (JSON, YAML flow collections)
    plus the most YAML block-sequence dashes on one line, or its XML elements, whichever is
    deeper. Brackets inside quoted strings do not count."""
    bare = _QUOTED.sub("", text)
    codes = np.frombuffer(bare.encode("utf-8", "replace"), np.uint8)
    step = np.zeros(len(codes), np.int64)
    step[(codes == ord("[")) | (codes == ord("{"))] = 1
    step[(codes == ord("]")) | (codes == ord("}"))] = -1
    brackets = int(np.cumsum(step).max(initial=0))
    dashes = max((m.group(1).count("-") for m in _DASHES.finditer(bare)), default=0)
    tags = np.array([-1 if m.group(1) else (0 if m.group(2) else 1) for m in _TAG.finditer(bare)], np.int64)
    elements = int(np.cumsum(tags).max(initial=0)) if len(tags) else 0
    return max(brackets + dashes, elements)


def read_bounded_text(path: str | os.PathLike, what: str, hint: str, encoding: str = "utf-8") -> str:
    """The text of ``path`` (a ``what``: "target file", "intrinsics file"), refused in one line
    (with ``hint``: what to give instead) when it is larger than :data:`MAX_SMALL_FILE_BYTES`
    or nests deeper than :data:`MAX_NESTING`. Read and decoding errors are the caller's."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_SMALL_FILE_BYTES:
        raise StereoseedError(f"{path}: {size} bytes, too large for a {what} (at most {MAX_SMALL_FILE_BYTES}); {hint}")
    with open(path, encoding=encoding) as f:
        text = f.read(MAX_SMALL_FILE_BYTES + 1)  # a file that grew since stat() is not read on
    if len(text) > MAX_SMALL_FILE_BYTES:
        raise StereoseedError(f"{path}: too large for a {what} (at most {MAX_SMALL_FILE_BYTES} bytes); {hint}")
    depth = nesting_depth(text)
    if depth > MAX_NESTING:
        raise StereoseedError(f"{path}: nested {depth} levels deep, more than any {what} ({MAX_NESTING} at most); "
                              f"{hint}")
    return text
