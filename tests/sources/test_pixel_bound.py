"""Pixels bounded before decoding, and a folder's frame size from most of its images (issue 34).

A 330 kB PNG of 20000x15000 took > 120 s and 2.6 GB for one frame: only the file's size was bounded. A
stray 1x1 image sorted first set the folder's frame size, and the camera error that followed named no file.
"""

from __future__ import annotations

import struct
import time
import zlib
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.errors import SourceError
from ar_anchor.sources import ImageFolderSource, VideoFileSource
from ar_anchor.sources.image_header import MAX_IMAGE_PIXELS, image_size
from tests.helpers import assert_clean_exit, error_lines, run_main


def huge_png(path: Path, width: int = 20000, height: int = 15000) -> None:
    """A PNG whose header says ``width`` x ``height`` (its data a few rows only: were it decoded, the decoder
    would first allocate the whole image; refused by its header, it never is)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress((b"\x00" + bytes(3 * width)) * 4, 9)
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


@pytest.fixture
def camera_file(tmp_path: Path) -> Path:
    path = tmp_path / "cam.yml"
    CameraModel.from_fov(320, 240, 60.0).to_yaml(path)
    return path


def _grey(width: int, height: int, shade: int = 90) -> np.ndarray:
    image = np.full((height, width, 3), shade, np.uint8)
    cv2.circle(image, (width // 2, height // 2), max(1, height // 4), (255, 255, 255), -1)
    return image


# ---------------------------------------------------------------------------- the header


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".bmp", ".webp", ".ppm", ".pgm", ".tif"])
@pytest.mark.parametrize("size", [(53, 37), (1, 1), (801, 600)])
def test_the_header_gives_the_size_the_decoder_gives(tmp_path, suffix, size):
    image = np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    if suffix == ".pgm":
        image = image[..., 0]
    path = tmp_path / f"x{suffix}"
    assert cv2.imwrite(str(path), image)
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image_size(path) == (decoded.shape[1], decoded.shape[0]) == size


def test_a_jpeg_header_is_found_past_its_exif_and_comments(tmp_path):
    ok, data = cv2.imencode(".jpg", _grey(64, 48))
    assert ok
    data = data.tobytes()
    exif = b"\xff\xe1" + struct.pack(">H", 2 + 60000) + b"Exif\x00\x00" + bytes(59994)  # a big APP1 first
    comment = b"\xff\xfe" + struct.pack(">H", 7) + b"hello"
    path = tmp_path / "exif.jpg"
    path.write_bytes(data[:2] + exif + comment + data[2:])
    assert image_size(path) == (64, 48)
    assert cv2.imread(str(path)).shape[:2] == (48, 64)


@pytest.mark.parametrize(
    "content",
    [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"\xff\xd8\xff\xda\x00\x02", b"BM" + bytes(40), b"P6 12", b"junk" * 8],
    ids=["empty", "png-cut", "jpeg-cut", "jpeg-scan-first", "bmp-zero", "pnm-cut", "junk"],
)
def test_a_header_that_does_not_parse_gives_none(tmp_path, content):
    path = tmp_path / "bad.img"
    path.write_bytes(content)
    assert image_size(path) is None


def test_a_named_pipe_or_a_folder_has_no_header_and_nothing_blocks(tmp_path):
    import os

    os.mkfifo(tmp_path / "pipe.png")
    started = time.perf_counter()
    assert image_size(tmp_path / "pipe.png") is None and image_size(tmp_path) is None
    assert image_size(tmp_path / "missing.png") is None
    assert time.perf_counter() - started < 1


def test_a_huge_png_header_is_read_in_microseconds_without_decoding(tmp_path):
    huge_png(tmp_path / "huge.png")
    started = time.perf_counter()
    assert image_size(tmp_path / "huge.png") == (20000, 15000)
    assert time.perf_counter() - started < 0.1


# ---------------------------------------------------------------------------- the bound


def test_an_image_of_too_many_pixels_in_a_folder_is_skipped_by_name_with_the_limit(tmp_path, caplog):
    huge_png(tmp_path / "f_0.png")
    for index in (1, 2):
        assert cv2.imwrite(str(tmp_path / f"f_{index}.png"), _grey(320, 240))
    started = time.perf_counter()
    with ImageFolderSource(tmp_path) as source:
        frames = list(source)
    assert time.perf_counter() - started < 10
    assert [f.index for f in frames] == [1, 2] and source.resolution == (320, 240) and source.skipped == 1
    assert "f_0.png: 20000x15000 pixels (300 MP), more than the 50 MP limit (--max-megapixels), skipped" in caplog.text


def test_replay_of_one_image_of_too_many_pixels_is_one_line_and_exit_2(tmp_path, camera_file):
    huge_png(tmp_path / "big.png")
    result = run_main(
        ["-q", "replay", str(tmp_path / "big.png"), "--camera", str(camera_file), "--out", str(tmp_path / "o")]
    )
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    assert result.stderr.strip().splitlines() == [
        f"ar-anchor: error: {tmp_path / 'big.png'}: 20000x15000 pixels (300 MP), more than the 50 MP limit "
        "(--max-megapixels)"
    ]


def test_max_megapixels_moves_the_limit(tmp_path, camera_file):
    huge_png(tmp_path / "f_0.png", 600, 400)  # 0.24 MP
    assert cv2.imwrite(str(tmp_path / "f_1.png"), _grey(400, 300))  # 0.12 MP
    with ImageFolderSource(tmp_path, max_pixels=200_000) as source:
        assert [f.index for f in source] == [1] and source.skipped == 1
    # raised: the header passes, and the (truncated) image is decoded, then found unreadable as before;
    # no image of the size most headers give (a tie: the first) decodes, so the first readable one sets it
    with ImageFolderSource(tmp_path, max_pixels=MAX_IMAGE_PIXELS) as source:
        assert source.resolution == (400, 300) and [f.index for f in source] == [1] and source.skipped == 1
    big = tmp_path / "big"
    big.mkdir()
    assert cv2.imwrite(str(big / "a.png"), _grey(400, 300))
    argv = ["-q", "replay", str(big), "--camera", str(camera_file), "--out", str(tmp_path / "o")]
    result = run_main([*argv, "--max-megapixels", "0.1"])
    assert result.code == 2 and error_lines(result.stderr) == [
        f"ar-anchor: error: {big}: none of its 1 image file(s) can be decoded (the last, a.png: 400x300 pixels "
        "(0.12 MP), more than the 0.1 MP limit (--max-megapixels))"
    ], result.describe()
    argv[2] = str(big / "a.png")
    result = run_main([*argv, "--max-megapixels", "0.1"])
    assert result.code == 2 and result.stderr.strip().splitlines() == [
        f"ar-anchor: error: {big / 'a.png'}: 400x300 pixels (0.12 MP), more than the 0.1 MP limit (--max-megapixels)"
    ], result.describe()
    assert run_main([*argv, "--max-megapixels", "0.2"]).code == 0


def test_a_video_of_frames_above_the_limit_is_refused_before_decoding(tmp_path):
    path = tmp_path / "clip.mkv"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mjpeg", rate=30)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuvj420p"
        for _ in range(2):
            for packet in stream.encode(av.VideoFrame.from_ndarray(_grey(320, 240), format="bgr24")):
                out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)
    with pytest.raises(
        SourceError, match=r"clip\.mkv: frames of 320x240 pixels \(0\.0768 MP\), more than the 0\.05 MP limit"
    ):
        VideoFileSource(path, max_pixels=50_000)
    with VideoFileSource(path) as source:
        assert source.resolution == (320, 240)


# ---------------------------------------------------------------------------- a stray image of another size


def test_a_stray_tiny_image_sorted_first_is_skipped_by_name_not_the_folder(tmp_path, camera_file):
    shots = tmp_path / "shots"
    shots.mkdir()
    assert cv2.imwrite(str(shots / "a_0.png"), np.zeros((1, 1, 3), np.uint8))
    for index in range(1, 4):
        assert cv2.imwrite(str(shots / f"f_{index}.png"), _grey(320, 240, 40 * index))
    result = run_main(["replay", str(shots), "--camera", str(camera_file), "--out", str(tmp_path / "o")])
    assert_clean_exit(result)
    assert result.code == 0, result.describe()
    assert (
        f"ar-anchor: WARNING: {shots / 'a_0.png'}: size 1x1 differs from the folder's 320x240 (most of its images), "
        "skipped"
    ) in result.stderr.splitlines()
    assert not error_lines(result.stderr)


def test_a_camera_that_does_not_fit_the_images_names_the_image_whose_size_it_is(tmp_path, camera_file):
    shots = tmp_path / "shots"
    shots.mkdir()
    assert cv2.imwrite(str(shots / "a_0.png"), np.zeros((1, 1, 3), np.uint8))
    result = run_main(["-q", "replay", str(shots), "--camera", str(camera_file), "--out", str(tmp_path / "o")])
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"ar-anchor: error: --camera {camera_file}: camera calibrated at 320x240")
    assert f"(the size of {shots / 'a_0.png'})" in line
