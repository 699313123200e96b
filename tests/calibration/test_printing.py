"""Printing the target: PNG pages carrying their resolution, a true-scale PDF per page, the box
size said, and an output folder holding someone else's files left alone."""
from __future__ import annotations

import re
import struct
import zlib

import cv2
import numpy as np
import pytest

from cli_helpers import one_line_error
from stereoseed.calibration.printing import DPI, PAPER_MM, TARGET_RECORD, box_size_mm, pdf_page, png_with_dpi
from stereoseed.cli import main


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """The PNG's chunks (type, data), their CRCs checked."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, pos = [], 8
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        assert struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0] == zlib.crc32(kind + body) & 0xFFFFFFFF
        out.append((kind, body))
        pos += 12 + length
    return out


def test_a_png_page_carries_its_dpi_and_decodes_to_the_same_pixels():
    page = np.random.default_rng(0).integers(0, 256, (70, 50), dtype=np.uint8)
    data = png_with_dpi(page, 300)
    chunks = _chunks(data)
    assert [k for k, _ in chunks][:3] == [b"IHDR", b"pHYs", b"IDAT"] and chunks[-1][0] == b"IEND"
    ppm_x, ppm_y, unit = struct.unpack(">IIB", chunks[1][1])
    assert ppm_x == ppm_y == 11811 and unit == 1  # 300 dpi = 11811 pixels a metre
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), page)


def _pdf_objects(data: bytes) -> dict[int, bytes]:
    """The PDF's objects by number, each found where the cross-reference table says it is."""
    start = int(re.search(rb"startxref\n(\d+)\n%%EOF\n$", data).group(1))
    table = data[start:].split(b"trailer")[0].split(b"\n")
    assert table[0] == b"xref"
    first, count = map(int, table[1].split())
    objects = {}
    for n, row in enumerate(table[3:2 + count], first + 1):
        offset = int(row.split()[0])
        assert data[offset:].startswith(f"{n} 0 obj\n".encode())
        objects[n] = data[offset:data.index(b"endobj", offset)]
    return objects


def test_a_pdf_page_is_the_image_at_true_scale():
    page = np.random.default_rng(1).integers(0, 256, (3508, 2480), dtype=np.uint8)  # A4 at 300 dpi
    data = pdf_page(page, 300)
    assert data.startswith(b"%PDF-1.4\n")
    objects = _pdf_objects(data)
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", objects[3]).group(1).split()]
    assert box[:2] == [0, 0] and abs(box[2] / 72 * 25.4 - 2480 * 25.4 / 300) < 1e-3  # 209.97 mm wide
    assert abs(box[3] / 72 * 25.4 - 3508 * 25.4 / 300) < 1e-3  # 297.0 mm high
    image = objects[5]
    assert b"/Width 2480 /Height 3508 /ColorSpace /DeviceGray /BitsPerComponent 8" in image
    length = int(re.search(rb"/Length (\d+)", image).group(1))
    stream = image[image.index(b"stream\n") + 7:][:length]
    np.testing.assert_array_equal(np.frombuffer(zlib.decompress(stream), np.uint8).reshape(page.shape), page)
    assert b"/Im0 Do" in objects[4]


def test_target_writes_pages_pdfs_and_says_the_box(tmp_path, capsys):
    out = tmp_path / "t"
    assert main(["target", "--out", str(out), "--size", "A4", "--faces", "3"]) == 0
    printed = capsys.readouterr().out
    x, y, z = box_size_mm("A4", 3)
    assert (x, y, z) == (PAPER_MM["A4"][0], PAPER_MM["A4"][1], PAPER_MM["A4"][1])
    assert f"box of at least {x:.0f} x {y:.0f} x {z:.0f} mm" in printed and "face_2.png/.pdf" in printed
    for k in range(3):
        png = (out / f"face_{k}.png").read_bytes()
        assert dict(_chunks(png))[b"pHYs"] == struct.pack(">IIB", 11811, 11811, 1)
        page = cv2.imread(str(out / f"face_{k}.png"), cv2.IMREAD_GRAYSCALE)
        objects = _pdf_objects((out / f"face_{k}.pdf").read_bytes())
        assert f"/Width {page.shape[1]} /Height {page.shape[0]}".encode() in objects[5] and DPI == 300
    # a rerun with two faces replaces the three-face target whole: no page 2 left behind
    assert main(["target", "--out", str(out), "--faces", "2"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [TARGET_RECORD, "assembly.png", "face_0.pdf", "face_0.png",
                                                     "face_1.pdf", "face_1.png", "target.json"]


@pytest.mark.parametrize("force", [False, True])
def test_target_never_replaces_or_removes_a_file_it_did_not_write(tmp_path, capsys, force):
    """Issue 48 row 2: the user's target.json and face_7.png in the folder stay as they are, with
    or without --force (which writes beside other files, never over them); so does a page
    stereoseed wrote that the user edited since."""
    out = tmp_path / "t"
    out.mkdir()
    (out / "target.json").write_text("mine")
    (out / "face_7.png").write_text("x")
    code = main(["target", "--out", str(out)] + (["--force"] if force else []))
    err = capsys.readouterr().err
    assert code == 2 and one_line_error(err) and ("target.json" in err or "face_7.png" in err)
    assert (out / "target.json").read_text() == "mine" and (out / "face_7.png").read_text() == "x"
    assert sorted(p.name for p in out.iterdir()) == ["face_7.png", "target.json"]

    fresh = tmp_path / "fresh"
    assert main(["target", "--out", str(fresh), "--faces", "2"]) == 0
    (fresh / "face_1.pdf").write_bytes(b"edited")
    code = main(["target", "--out", str(fresh), "--faces", "2"] + (["--force"] if force else []))
    err = capsys.readouterr().err
    assert code == 2 and one_line_error(err) and "face_1.pdf: stereoseed target did not write it" in err
    assert (fresh / "face_1.pdf").read_bytes() == b"edited"
    record = tmp_path / "rec" / TARGET_RECORD  # a file of the record's name that is no record: left alone
    record.parent.mkdir()
    record.write_text("mine")
    code = main(["target", "--out", str(record.parent)] + (["--force"] if force else []))
    err = capsys.readouterr().err
    assert code == 2 and one_line_error(err) and "is not the record stereoseed target keeps" in err
    assert record.read_text() == "mine"


@pytest.mark.parametrize("force", [False, True])
def test_target_leaves_a_folder_of_other_files_alone_unless_forced(tmp_path, capsys, force):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"not ours")
    code = main(["target", "--out", str(out)] + (["--force"] if force else []))
    err = capsys.readouterr().err
    if force:
        assert code == 0 and (out / "target.json").is_file()
    else:
        assert code == 2 and err.count("\n") == 1 and "holiday.jpg" in err and "--force" in err
        assert sorted(p.name for p in out.iterdir()) == ["holiday.jpg"]
    assert (out / "holiday.jpg").read_bytes() == b"not ours"
