"""``ar-anchor markers``: printed geometry measured back from the output, config snippets, errors.

PDFs are rasterised with pypdfium2 at 600 dpi and the markers detected with OpenCV (sub-pixel
corners); every length is then compared with the requested one in mm. PNGs are detected directly;
SVGs are parsed as XML.
"""

from __future__ import annotations

import math
import re
import struct
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.cli.main import build_parser
from ar_anchor.config import load_config
from ar_anchor.errors import InputError
from ar_anchor.tools.markers import (
    MarkerSheet,
    marker_bits,
    marker_rects,
    parse_ids,
    rasterise_page,
    render_pdf,
    render_png,
    render_svg,
    run_markers,
    sheet_from_args,
    write_sheet,
)

REPO = Path(__file__).resolve().parents[2]
PDF_DPI = 600
PX_PER_MM = PDF_DPI / 25.4
TOL_MM = 0.1
SVG_NS = {"svg": "http://www.w3.org/2000/svg"}


# ---------------------------------------------------------------------------- helpers


def rasterise_pdf(data: bytes, dpi: int = PDF_DPI) -> list[np.ndarray]:
    pdfium = pytest.importorskip("pypdfium2", reason="pypdfium2 rasterises the PDFs (test extra)")
    document = pdfium.PdfDocument(data)
    pages = []
    for page in document:
        image = page.render(scale=dpi / 72.0, grayscale=True).to_numpy()
        pages.append(image if image.ndim == 2 else image[..., 0])
    return pages


def pdf_page_sizes_pt(data: bytes) -> list[tuple[float, float]]:
    pdfium = pytest.importorskip("pypdfium2", reason="pypdfium2 rasterises the PDFs (test extra)")
    return [tuple(page.get_size()) for page in pdfium.PdfDocument(data)]


def detector_parameters() -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return params


def detect(image: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    """Marker id -> its four corners (TL, TR, BR, BL) in pixels."""
    cv_dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    corners, ids, _ = cv2.aruco.ArucoDetector(cv_dictionary, detector_parameters()).detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) for i, c in zip(ids.ravel(), corners)}


def side_px(corners: np.ndarray) -> float:
    """Mean of the four edge lengths."""
    return float(np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))


def pixel_to_mm(points: np.ndarray, px_per_mm: float = PX_PER_MM) -> np.ndarray:
    """Pixel coordinates (OpenCV: pixel centres at integers) -> page mm."""
    return (np.asarray(points, dtype=np.float64) + 0.5) / px_per_mm


def ruler_length_mm(image: np.ndarray, sheet: MarkerSheet, page_index: int = 0) -> float:
    """Length of the scale bar: the ink along one row through the bar's middle (grey levels = coverage)."""
    (bar,) = sheet.pages()[page_index].fills("ruler-bar")
    x, y, w, h = bar.rects[0]
    row = int((y + h / 2) * PX_PER_MM)
    lo, hi = int((x - 3) * PX_PER_MM), int((x + w + 3) * PX_PER_MM)
    ink = (255.0 - image[row, lo:hi].astype(np.float64)) / 255.0
    return float(ink.sum()) / PX_PER_MM


def path_rects(d: str) -> list[tuple[float, float, float, float]]:
    rects = []
    for m in re.finditer(r"M([-\d.]+) ([-\d.]+)h([-\d.]+)v([-\d.]+)h([-\d.]+)z", d):
        x, y, w, h, back = map(float, m.groups())
        assert back == pytest.approx(-w)
        rects.append((x, y, w, h))
    assert rects, f"no rectangles in path data {d[:80]!r}"
    return rects


def png_dpi(data: bytes) -> float | None:
    """The pHYs chunk's resolution in dots per inch (None without one)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    offset = 8
    while offset < len(data):
        (length,) = struct.unpack(">I", data[offset : offset + 4])
        kind = data[offset + 4 : offset + 8]
        if kind == b"pHYs":
            x, y, unit = struct.unpack(">IIB", data[offset + 8 : offset + 17])
            assert unit == 1 and x == y
            return x * 0.0254
        offset += 12 + length
    return None


def markers_args(*argv: str):
    return build_parser().parse_args(["markers", *argv])


# ---------------------------------------------------------------------------- ids and bits


def test_parse_ids() -> None:
    assert parse_ids("0-3") == (0, 1, 2, 3)
    assert parse_ids("0,5,7") == (0, 5, 7)
    assert parse_ids(" 9, 0-3 ") == (0, 1, 2, 3, 9)
    for bad in ("", "a", "3-1", "1,,2", "-1", "1,1", "0-3,2"):
        with pytest.raises(InputError, match="--ids"):
            parse_ids(bad)


@pytest.mark.parametrize(("dictionary", "marker_id"), [("DICT_4X4_50", 3), ("DICT_6X6_250", 117), ("DICT_5X5_100", 0)])
def test_marker_rects_are_the_bit_matrix(dictionary: str, marker_id: int) -> None:
    """The rectangles cover exactly the black modules, with edges at exact multiples of side/modules."""
    bits = np.array(marker_bits(dictionary, marker_id))
    n = bits.shape[0]
    cv_dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    assert n == cv_dictionary.markerSize + 2
    assert bits[0].all() and bits[-1].all() and bits[:, 0].all() and bits[:, -1].all()  # the black border
    side, x0, y0 = 37.0, 11.5, 20.25
    module = side / n
    covered = np.zeros_like(bits, dtype=int)
    for x, y, w, h in marker_rects(bits, x0, y0, side):
        c0, r0 = (x - x0) / module, (y - y0) / module
        c1, r1 = c0 + w / module, r0 + h / module
        for value in (c0, r0, c1, r1):
            assert value == pytest.approx(round(value), abs=1e-9)
        covered[round(r0) : round(r1), round(c0) : round(c1)] += 1
    assert np.array_equal(covered, bits.astype(int)), "rectangles overlap or miss modules"
    # the image the bits came from decodes as this id
    image = np.kron(np.where(bits, 0, 255).astype(np.uint8), np.ones((10, 10), np.uint8))
    image = cv2.copyMakeBorder(image, 20, 20, 20, 20, cv2.BORDER_CONSTANT, value=255)
    assert list(detect(image, dictionary)) == [marker_id]


# ---------------------------------------------------------------------------- PDF: measured geometry


def test_single_marker_pdf_exact_size(tmp_path: Path) -> None:
    sheet = MarkerSheet.single("DICT_4X4_50", [3], 50.0)
    data = render_pdf(sheet)
    assert b"/Subtype /Image" not in data and b"/XObject" not in data, "markers must be vector, not raster"
    assert b"/PrintScaling /None" in data
    assert render_pdf(sheet) == data, "the same sheet must give the same bytes"
    assert pdf_page_sizes_pt(data) == [pytest.approx((210 / 25.4 * 72, 297 / 25.4 * 72), abs=0.01)]

    (image,) = rasterise_pdf(data)
    found = detect(image, "DICT_4X4_50")
    assert list(found) == [3]
    measured = side_px(found[3]) / PX_PER_MM
    print(f"single 50 mm marker at {PDF_DPI} dpi: {measured:.4f} mm")
    assert measured == pytest.approx(50.0, abs=TOL_MM)
    # and where the layout put it
    (item,) = sheet.pages()[0].markers
    expected = np.array([[item.x, item.y], [item.x + 50, item.y], [item.x + 50, item.y + 50], [item.x, item.y + 50]])
    assert np.abs(pixel_to_mm(found[3]) - expected).max() < TOL_MM

    ruler = ruler_length_mm(image, sheet)
    print(f"ruler: {ruler:.4f} mm")
    assert ruler == pytest.approx(100.0, abs=TOL_MM)


def test_single_markers_fill_pages(tmp_path: Path) -> None:
    """Ten 50 mm markers: several per page, more pages as needed, each marker found at its size."""
    sheet = MarkerSheet.single("DICT_4X4_50", "0-9", 50.0)
    pages = sheet.pages()
    assert len(pages) >= 2 and all(len(p.markers) >= 4 for p in pages[:-1])
    assert sorted(m.marker_id for p in pages for m in p.markers) == list(range(10))
    for page in pages:  # quiet zone: at least one module of white around each marker (and no overlap)
        boxes = [(m.x - sheet.module_mm, m.y - sheet.module_mm, m.side + 2 * sheet.module_mm) for m in page.markers]
        for i, (ax, ay, aside) in enumerate(boxes):
            assert 0 < ax and ax + aside < page.width and 0 < ay and ay + aside < page.height
            for bx, by, bside in boxes[i + 1 :]:
                assert ax + aside <= bx or bx + bside <= ax or ay + aside <= by or by + bside <= ay
    images = rasterise_pdf(render_pdf(sheet), dpi=300)
    assert len(images) == len(pages)
    found = {}
    for image in images:
        found.update(detect(image, "DICT_4X4_50"))
    assert sorted(found) == list(range(10))
    for corners in found.values():
        assert side_px(corners) / (300 / 25.4) == pytest.approx(50.0, abs=TOL_MM)


def board_fit_error_mm(detected: dict[int, np.ndarray], expected_mm: dict[int, np.ndarray]) -> float:
    """Largest distance (mm) between detected corners and the expected page positions."""
    errors = [np.abs(pixel_to_mm(detected[i]) - expected_mm[i]).max() for i in expected_mm]
    return float(max(errors))


def test_grid_board_pdf_geometry(tmp_path: Path) -> None:
    sheet = MarkerSheet.grid("DICT_4X4_50", 2, 2, 40.0, 20.0, first_id=10, name="desk")
    paths = write_sheet(sheet, tmp_path)
    (image,) = rasterise_pdf(paths[0].read_bytes())
    found = detect(image, "DICT_4X4_50")
    assert sorted(found) == [10, 11, 12, 13]
    sides = [side_px(c) / PX_PER_MM for c in found.values()]
    gaps = [
        (found[11][0, 0] - found[10][1, 0]) / PX_PER_MM,  # TL of the right marker - TR of the left one
        (found[13][3, 0] - found[12][2, 0]) / PX_PER_MM,
        (found[12][0, 1] - found[10][3, 1]) / PX_PER_MM,  # TL of the lower marker - BL of the upper one
        (found[13][1, 1] - found[11][2, 1]) / PX_PER_MM,
    ]
    print(f"grid sides {np.round(sides, 4)} mm, gaps {np.round(gaps, 4)} mm")
    assert np.allclose(sides, 40.0, atol=TOL_MM)
    assert np.allclose(gaps, 20.0, atol=TOL_MM)

    # the config snippet's board, placed at the board's origin on the page, is what was printed
    config = load_config(paths[-1])
    (board,) = config.boards
    ox, oy = sheet.board_origin_mm()
    expected = {i: c[:, :2] * 1000.0 + [ox, oy] for i, c in board.corners_in_board().items()}
    error = board_fit_error_mm(found, expected)
    print(f"grid: largest corner error against the config geometry {error:.4f} mm")
    assert error < TOL_MM


def charuco_detect(image: np.ndarray, sheet: MarkerSheet):
    detector = cv2.aruco.CharucoDetector(sheet.cv_board(), cv2.aruco.CharucoParameters(), detector_parameters())
    corners, ids, _, marker_ids = detector.detectBoard(image)
    if ids is None:
        return {}, marker_ids
    return {int(i): c.ravel().astype(np.float64) for i, c in zip(ids.ravel(), corners)}, marker_ids


@pytest.mark.parametrize("legacy", [False, True])
def test_charuco_pdf_geometry_and_legacy(tmp_path: Path, legacy: bool) -> None:
    """5x6 squares (an even number of rows, where the legacy pattern differs)."""
    sheet = MarkerSheet.charuco("DICT_5X5_100", 5, 6, 30.0, 22.0, legacy=legacy)
    other = MarkerSheet.charuco("DICT_5X5_100", 5, 6, 30.0, 22.0, legacy=not legacy)
    paths = write_sheet(sheet, tmp_path)
    (image,) = rasterise_pdf(paths[0].read_bytes())

    corners, marker_ids = charuco_detect(image, sheet)
    assert len(marker_ids) == 15
    assert sorted(corners) == list(range(4 * 5)), "every inner chessboard corner"
    steps = []
    for corner_id, point in corners.items():
        row, col = divmod(corner_id, 4)
        if col < 3:
            steps.append(np.linalg.norm(corners[corner_id + 1] - point))
        if row < 4:
            steps.append(np.linalg.norm(corners[corner_id + 4] - point))
    steps_mm = np.array(steps) / PX_PER_MM
    print(
        f"charuco legacy={legacy}: square {steps_mm.mean():.4f} mm (min {steps_mm.min():.4f}, max {steps_mm.max():.4f})"
    )
    assert np.allclose(steps_mm, 30.0, atol=TOL_MM)
    for corners_of_marker in detect(image, "DICT_5X5_100").values():
        assert side_px(corners_of_marker) / PX_PER_MM == pytest.approx(22.0, abs=TOL_MM)

    # the config snippet's board gives the same chessboard corners
    (board,) = load_config(paths[-1]).boards
    assert board.legacy is legacy
    ox, oy = sheet.board_origin_mm()
    expected = np.asarray(board.cv_board().getChessboardCorners())[:, :2] * 1000.0 + [ox, oy]
    measured = pixel_to_mm(np.array([corners[i] for i in range(20)]))
    error = float(np.abs(measured - expected).max())
    print(f"charuco legacy={legacy}: largest corner error against the config geometry {error:.4f} mm")
    assert error < TOL_MM

    # the other pattern does not match the printed board
    other_corners, _ = charuco_detect(image, other)
    assert len(other_corners) < len(corners) // 2


@pytest.mark.parametrize("kind, legacy", [("grid", False), ("charuco", False), ("charuco", True)])
def test_board_pattern_is_opencvs(kind: str, legacy: bool) -> None:
    """At 254 dpi (10 px/mm) with whole-pixel modules, the rendered board is pixel-identical to the board's
    own ``generateImage``."""
    if kind == "grid":  # (grid boards have no legacy pattern)
        sheet = MarkerSheet.grid("DICT_4X4_50", 3, 2, 18.0, 9.0, first_id=4)
    else:
        sheet = MarkerSheet.charuco("DICT_4X4_50", 5, 4, 12.0, 9.0, legacy=legacy)
    image = rasterise_page(sheet.pages("png", 254)[0], 254)
    width, height = sheet.board_size_mm
    ox, oy = sheet.board_origin_mm()
    x0, y0 = math.floor(ox * 10 + 0.5), math.floor(oy * 10 + 0.5)  # the renderer rounds halves up
    ours = image[y0 : y0 + round(height * 10), x0 : x0 + round(width * 10)]
    theirs = sheet.cv_board().generateImage((round(width * 10), round(height * 10)), marginSize=0, borderBits=1)
    assert ours.shape == theirs.shape
    assert np.array_equal(ours, theirs)


def test_too_large_is_an_error_not_a_scaled_print() -> None:
    with pytest.raises(InputError, match=r"--size-mm: a 200 mm marker .* a4 paper"):
        MarkerSheet.single("DICT_4X4_50", [0], 200.0).pages()
    with pytest.raises(InputError, match=r"--cols/--rows/--size-mm/--gap-mm: the 4x4 grid board is 230 x 230 mm"):
        MarkerSheet.grid("DICT_4X4_50", 4, 4, 50.0, 10.0).pages()
    with pytest.raises(InputError, match=r"--cols/--rows/--square-mm: the 8x10 charuco board is 320 x 400 mm"):
        MarkerSheet.charuco("DICT_6X6_250", 8, 10, 40.0, 30.0).pages()
    # a4 has 185 mm across for a cut box: a 138 mm 4x4 marker (184 mm with its quiet zone) fits, 140 mm
    # (186.7 mm) does not, and fits the wider letter paper
    assert len(MarkerSheet.single("DICT_4X4_50", [0], 138.0).pages()) == 1
    with pytest.raises(InputError, match="a4 paper"):
        MarkerSheet.single("DICT_4X4_50", [0], 140.0).pages()
    assert len(MarkerSheet.single("DICT_4X4_50", [0], 140.0, paper="letter").pages()) == 1


def test_wide_board_goes_landscape() -> None:
    sheet = MarkerSheet.grid("DICT_4X4_50", 4, 1, 45.0, 6.0)  # 198 mm wide: portrait a4 has 185 mm
    (page,) = sheet.pages()
    assert page.landscape and (page.width, page.height) == (297.0, 210.0)
    assert pdf_page_sizes_pt(render_pdf(sheet)) == [pytest.approx((297 / 25.4 * 72, 210 / 25.4 * 72), abs=0.01)]


# ---------------------------------------------------------------------------- PNG


@pytest.mark.parametrize("dpi", [200, 300])
@pytest.mark.parametrize("size_mm", [37.0, 38.1])  # 38.1 mm: whole-pixel modules at both; 37 mm: rounded edges
def test_png_at_dpi(tmp_path: Path, dpi: int, size_mm: float) -> None:
    sheet = MarkerSheet.single("DICT_4X4_50", [0, 1], size_mm)
    paths = write_sheet(sheet, tmp_path, "png", dpi)
    assert [p.name for p in paths] == [
        f"DICT_4X4_50_ids0-1_{size_mm:g}mm_{dpi}dpi.png",
        f"DICT_4X4_50_ids0-1_{size_mm:g}mm_{dpi}dpi.toml",
    ]
    data = paths[0].read_bytes()
    assert png_dpi(data) == pytest.approx(dpi, abs=0.01)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image.shape == (round(297 / 25.4 * dpi), round(210 / 25.4 * dpi))
    exact = size_mm / 25.4 * dpi
    found = detect(image, "DICT_4X4_50")
    assert sorted(found) == [0, 1]
    for marker_id, corners in found.items():
        measured = side_px(corners)
        print(f"png {dpi} dpi {size_mm:g} mm id {marker_id}: side {measured:.3f} px, exact {exact:.3f} px")
        assert abs(measured - exact) <= 1.0
        # the printed square itself (ink extent along the marker's middle row and column)
        item = next(m for m in sheet.pages()[0].markers if m.marker_id == marker_id)
        row = image[round((item.y + 0.5 * sheet.module_mm) * dpi / 25.4)]
        col = image[:, round((item.x + 0.5 * sheet.module_mm) * dpi / 25.4)]
        x_lo, y_lo = round((item.x - 2) * dpi / 25.4), round((item.y - 2) * dpi / 25.4)
        span = round((item.side + 4) * dpi / 25.4)
        assert abs(np.count_nonzero(row[x_lo : x_lo + span] == 0) - exact) <= 1.0
        assert abs(np.count_nonzero(col[y_lo : y_lo + span] == 0) - exact) <= 1.0


def test_png_pages_are_numbered(tmp_path: Path) -> None:
    sheet = MarkerSheet.single("DICT_4X4_50", "0-9", 50.0)
    paths = write_sheet(sheet, tmp_path, "png", 100)
    count = len(sheet.pages())
    assert count >= 2
    names = [p.name for p in paths]
    assert names == [f"DICT_4X4_50_ids0-9_50mm_100dpi_p{n}.png" for n in range(1, count + 1)] + [
        "DICT_4X4_50_ids0-9_50mm_100dpi.toml"
    ]


def test_png_refuses_modules_below_two_pixels() -> None:
    with pytest.raises(InputError, match="--dpi"):
        render_png(MarkerSheet.single("DICT_4X4_50", [0], 5.0), 50)


# ---------------------------------------------------------------------------- SVG


@pytest.mark.parametrize(
    ("paper", "size"),
    [("a4", ("210mm", "297mm", "0 0 210 297")), ("letter", ("215.9mm", "279.4mm", "0 0 215.9 279.4"))],
)
def test_svg_pages_and_marker_extent(paper: str, size: tuple[str, str, str]) -> None:
    sheet = MarkerSheet.single("DICT_6X6_250", "0-11", 30.0, paper=paper)
    documents = render_svg(sheet)
    assert len(documents) == len(sheet.pages()) >= 1
    seen = []
    for document in documents:
        root = ET.fromstring(document)
        assert (root.get("width"), root.get("height"), root.get("viewBox")) == size
        assert root.find(".//svg:image", SVG_NS) is None
        assert "this bar must measure 100 mm" in document and "Print at 100 % / actual size" in document
        for path in root.findall("svg:path[@class='marker']", SVG_NS):
            rects = np.array(path_rects(path.get("d")))
            x0, y0 = rects[:, 0].min(), rects[:, 1].min()
            x1, y1 = (rects[:, 0] + rects[:, 2]).max(), (rects[:, 1] + rects[:, 3]).max()
            assert x1 - x0 == pytest.approx(30.0, abs=1e-3) and y1 - y0 == pytest.approx(30.0, abs=1e-3)
            marker_id = int(path.get("data-id"))
            module = 30.0 / 8
            black_area = np.array(marker_bits("DICT_6X6_250", marker_id)).sum() * module**2
            assert (rects[:, 2] * rects[:, 3]).sum() == pytest.approx(black_area, rel=1e-4)
            seen.append(marker_id)
        (bar,) = root.findall("svg:path[@class='ruler-bar']", SVG_NS)
        ((_, _, bar_w, _),) = path_rects(bar.get("d"))
        assert bar_w == pytest.approx(100.0, abs=1e-6)
    assert sorted(seen) == list(range(12))


# ---------------------------------------------------------------------------- config snippets


def test_config_snippet_single(tmp_path: Path) -> None:
    sheet = MarkerSheet.single("dict_5x5_100", "3-5,42", 45.5)
    paths = write_sheet(sheet, tmp_path, "svg")
    toml = paths[-1]
    assert toml.name == "DICT_5X5_100_ids3-5+42_45.5mm.toml"
    config = load_config(toml)
    assert config.detector.dictionary == "DICT_5X5_100"
    assert config.markers.ids == (3, 4, 5, 42)
    assert config.markers.length_m == 0.0455 and dict(config.markers.lengths_m) == {}
    assert config.boards == ()
    assert all(config.marker_length(i) == 0.0455 for i in (3, 4, 5, 42))


def test_config_snippet_grid(tmp_path: Path) -> None:
    sheet = MarkerSheet.grid("DICT_4X4_50", 3, 2, 30.0, 7.5, first_id=20, name="shelf")
    paths = write_sheet(sheet, tmp_path)
    assert [p.name for p in paths] == [
        "shelf_3x2_DICT_4X4_50_ids20-25_30mm_gap7.5mm.pdf",
        "shelf_3x2_DICT_4X4_50_ids20-25_30mm_gap7.5mm.toml",
    ]
    (board,) = load_config(paths[-1]).boards
    assert (board.name, board.kind, board.cols, board.rows) == ("shelf", "grid", 3, 2)
    assert (board.marker_length_m, board.separation_m, board.marker_ids) == (0.03, 0.0075, tuple(range(20, 26)))
    ours = np.asarray(sheet.cv_board().getObjPoints(), dtype=np.float64).reshape(-1, 4, 3) / 1000.0
    theirs = np.array([board.corners_in_board()[i] for i in board.marker_ids])
    assert np.allclose(ours, theirs, atol=1e-12)


def test_config_snippet_charuco(tmp_path: Path) -> None:
    sheet = MarkerSheet.charuco("DICT_6X6_250", 5, 7, 25.0, 18.0, first_id=30, legacy=True, name="calib")
    paths = write_sheet(sheet, tmp_path, "png", 100)
    assert paths[-1].name == "calib_5x7_DICT_6X6_250_ids30-46_sq25mm_m18mm_legacy_100dpi.toml"
    config = load_config(paths[-1])
    (board,) = config.boards
    assert config.detector.dictionary == "DICT_6X6_250"
    assert (board.name, board.kind, board.cols, board.rows, board.legacy) == ("calib", "charuco", 5, 7, True)
    assert (board.square_length_m, board.marker_length_m, board.marker_ids) == (0.025, 0.018, tuple(range(30, 47)))
    ours, theirs = sheet.cv_board(), board.cv_board()
    assert np.allclose(np.asarray(ours.getChessboardCorners()) / 1000.0, theirs.getChessboardCorners(), atol=1e-9)
    assert np.allclose(np.asarray(ours.getObjPoints()) / 1000.0, np.asarray(theirs.getObjPoints()), atol=1e-9)


# ---------------------------------------------------------------------------- bad input


BAD_ARGS = [
    (["--ids", "0-3"], r"--marker-length: required"),
    (["--size-mm", "50"], r"--ids: nothing to print"),
    (["--ids", "0-3", "--size-mm", "50", "--cols", "2"], r"--cols: not used"),
    (["--ids", "0-3", "--size-mm", "50", "--first-id", "4"], r"--first-id: not used"),
    (["--ids", "0-3", "--size-mm", "50", "--legacy"], r"--legacy: not used"),
    (["--ids", "3-1", "--size-mm", "50"], r"--ids: range '3-1' runs backwards"),
    (["--ids", "0,x", "--size-mm", "50"], r"--ids: cannot read 'x'"),
    (["--ids", "48-52", "--size-mm", "20"], r"--ids: ids 50, 51, 52 are outside DICT_4X4_50"),
    (["--dictionary", "DICT_9X9_1", "--ids", "0", "--size-mm", "20"], r"--dictionary: unknown dictionary"),
    (["--board", "grid", "--cols", "2", "--rows", "2", "--size-mm", "40"], r"--gap-mm: required with --board grid"),
    (["--board", "grid", "--size-mm", "40", "--gap-mm", "10"], r"--cols, --rows: required with --board grid"),
    (["--board", "grid", "--cols", "2", "--rows", "2", "--size-mm", "4", "--gap-mm", "1", "--ids", "0"], r"--ids: not"),
    (["--board", "grid", "--cols", "8", "--rows", "8", "--size-mm", "10", "--gap-mm", "2"], r"--first-id: .*64 ids"),
    (["--board", "grid", "--cols", "2", "--rows", "2", "--size-mm", "9", "--gap-mm", "2", "--legacy"], r"--legacy"),
    (["--board", "grid", "--cols", "2", "--rows", "2", "--size-mm", "9", "--gap-mm", "2", "--name", "a b"], r"--name"),
    (["--board", "charuco", "--cols", "5", "--rows", "7", "--size-mm", "20"], r"--square-length: required"),
    (
        ["--board", "charuco", "--cols", "5", "--rows", "7", "--square-mm", "20", "--size-mm", "20"],
        r"--size-mm: .*smaller",
    ),
    (["--board", "charuco", "--cols", "1", "--rows", "7", "--square-mm", "20", "--size-mm", "10"], r"--cols: must be"),
    (
        ["--board", "charuco", "--cols", "5", "--rows", "5", "--square-mm", "9", "--size-mm", "5", "--gap-mm", "1"],
        r"--gap-mm",
    ),
    (["--ids", "0", "--size-mm", "260"], r"--size-mm: a 260 mm marker needs"),
    (["--ids", "0", "--size-mm", "5", "--format", "png", "--dpi", "50"], r"--dpi: at 50 dpi"),
]


@pytest.mark.parametrize(("argv", "message"), BAD_ARGS, ids=[" ".join(a) for a, _ in BAD_ARGS])
def test_bad_input_names_the_option(tmp_path: Path, argv: list[str], message: str) -> None:
    out = tmp_path / "sheets"
    with pytest.raises(InputError, match=message):
        run_markers(markers_args(*argv, "--out", str(out), "-q"))
    assert not out.exists(), "nothing is written for bad input"


def test_out_that_is_a_file(tmp_path: Path) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    for out in (blocker, blocker / "sub"):
        with pytest.raises(InputError, match="--out: .*a file, not a directory"):
            run_markers(markers_args("--ids", "0", "--size-mm", "30", "--out", str(out), "-q"))


def test_sheet_from_args_modes() -> None:
    sheet = sheet_from_args(markers_args("--ids", "0-1", "--size-mm", "30"))
    assert (sheet.kind, sheet.ids, sheet.marker_mm) == ("single", (0, 1), 30.0)
    sheet = sheet_from_args(
        markers_args("--board", "charuco", "--cols", "5", "--rows", "7", "--square-mm", "30", "--size-mm", "20")
    )
    assert (sheet.kind, sheet.name, sheet.ids) == ("charuco", "charuco", tuple(range(17)))


# ---------------------------------------------------------------------------- the command


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ar_anchor", "markers", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.slow
def test_cli_success_and_usage_error(tmp_path: Path) -> None:
    ok = run_cli(["--board", "grid", "--cols", "2", "--rows", "2", "--size-mm", "40", "--gap-mm", "20"], tmp_path)
    assert ok.returncode == 0, ok.stderr
    stem = "grid_2x2_DICT_4X4_50_ids0-3_40mm_gap20mm"
    for ext in ("pdf", "toml"):
        assert (tmp_path / "markers" / f"{stem}.{ext}").is_file()
        assert f"markers/{stem}.{ext}" in ok.stdout
    last = ok.stdout.strip().splitlines()[-1]  # the last line names every file written
    assert last == f"outputs: markers/{stem}.pdf, markers/{stem}.toml", ok.stdout
    assert load_config(tmp_path / "markers" / f"{stem}.toml").boards[0].marker_ids == (0, 1, 2, 3)

    bad = run_cli(["--ids", "0-3", "--out", "x"], tmp_path)
    assert bad.returncode == 2
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1 and "--marker-length" in lines[0], bad.stderr
    assert "Traceback" not in bad.stderr + bad.stdout
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------------------- the shipped sheets

SHIPPED = [  # markers/README.md: the commands that made markers/*
    ["--ids", "0-6,8-9", "--marker-length", "50mm"],
    ["--ids", "7", "--marker-length", "40mm"],
    "--board grid --cols 2 --rows 2 --marker-length 40mm --gap-mm 20 --first-id 10 --name desk".split(),
]


def test_shipped_sheets_match_the_demo_config() -> None:
    default = load_config(REPO / "configs" / "demo.toml")
    readme = (REPO / "markers" / "README.md").read_text(encoding="utf-8")
    for argv in SHIPPED:
        sheet = sheet_from_args(markers_args(*argv))
        stem = sheet.stem()
        assert " ".join(argv) in readme
        assert (REPO / "markers" / f"{stem}.pdf").is_file()
        toml = REPO / "markers" / f"{stem}.toml"
        assert toml.read_text(encoding="utf-8") == sheet.config_toml([f"{stem}.pdf"])
        snippet = load_config(toml)
        assert snippet.detector.dictionary == default.detector.dictionary
        if sheet.kind == "single":
            for marker_id in sheet.ids:
                assert default.board_of(marker_id) is None
                assert snippet.marker_length(marker_id) == default.marker_length(marker_id)
        else:
            (board,) = snippet.boards
            desk = next(b for b in default.boards if b.name == board.name)
            assert board.marker_ids == desk.marker_ids
            for marker_id, corners in board.corners_in_board().items():
                assert np.allclose(corners, desk.corners_in_board()[marker_id])
