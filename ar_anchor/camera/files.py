"""The camera files read: their checks before any parser sees them, and the readers of their values.

Files are OpenCV FileStorage YAML (or XML, JSON) with the keys OpenCV's calibration sample writes:
``camera_matrix`` (3x3), ``distortion_coefficients`` (1xN, N in 4, 5, 8, 12, 14),
``image_width``, ``image_height``. ROS ``camera_info`` YAML (``camera_calibration``'s output) has the
same keys with ``rows``/``cols``/``data`` maps in place of ``!!opencv-matrix``; it is read too, for the
distortion models OpenCV's pinhole model is (``plumb_bob``, ``rational_polynomial``). PhotonVision's
calibration JSON (its calibration page's export: ``resolution`` {width, height}, ``cameraIntrinsics`` and
``distCoeffs`` as {rows, cols, type, data}; before 2024 the distortion was named ``cameraExtrinsics``) is
read for its OpenCV lens model (``lensmodel`` LENSMODEL_OPENCV, not fisheye), as is a PhotonVision camera
settings file holding one such calibration (``calibrations``).

The input-file checks (:func:`input_file_problem`, :func:`opencv_path_problem`,
:func:`filestorage_nesting_problem`) serve every input file: camera, config, layout.
"""

from __future__ import annotations

import gzip
import io
import json
import math
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import CameraError, printable

__all__ = [
    "FORMATS_READ",
    "MAX_FILE_BYTES",
    "CameraFile",
    "filestorage_nesting_problem",
    "input_file_problem",
    "opencv_path_problem",
    "read_camera_file",
]

# ROS camera_info distortion models that are OpenCV's pinhole model (others, e.g. equidistant, are not)
_ROS_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")

# OpenCV's FileStorage parsers (YAML, JSON, XML) recurse once per nesting level and overflow the C
# stack (a segmentation fault, not an exception) somewhere past 20000 levels; real files nest a few.
MAX_NESTING = 1000
_OPENERS = re.compile(rb"[\[{]|[\]}]|</|/>|<[A-Za-z_]")
_MAX_DECOMPRESSED = 64 * 1024 * 1024
_ONE_CHANNEL_DT = re.compile(r"1?[ucwsifdh]")  # OpenCV's element types (uchar ... double, half)

# Input files (camera, config, layout) are small: a larger one is refused before it is read (a 2 GiB
# sparse file took a minute and gigabytes of memory to be read whole and then refused)
MAX_FILE_BYTES = 16 * 2**20
# ... except a PhotonVision calibration JSON: its board observations (older versions inline each snapshot as a
# base64 image) can make it larger; JSON is parsed by Python's json, not OpenCV
MAX_JSON_BYTES = 128 * 2**20

# what a camera file may be, for the error that finds none of them
FORMATS_READ = (
    "formats read: OpenCV FileStorage YAML, XML or JSON as `ar-anchor calibrate` writes; ROS camera_info YAML; "
    "PhotonVision calibration JSON"
)
_PHOTONVISION_LENS = "LENSMODEL_OPENCV"  # PhotonVision's OpenCV model; its mrcal stereographic ones are not


def input_file_problem(path: Path, max_bytes: int = MAX_FILE_BYTES) -> str | None:
    """Why ``path`` cannot be read as a small input file (a camera, config or layout file), or None.

    Looked up without opening it: not there, a directory, a FIFO, a device or a socket (opening a FIFO
    would wait for a writer), or larger than ``max_bytes``.
    """
    try:
        info = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        return "not found"
    except OSError as err:
        return f"cannot read ({err.strerror})"
    mode = info.st_mode
    if stat.S_ISDIR(mode):
        return "is a directory, not a file"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe), not a file"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "is a device, not a file"
    if not stat.S_ISREG(mode):
        return "is not a regular file"
    if info.st_size > max_bytes:
        return f"is {info.st_size / 2**20:.0f} MiB, too large to be one (at most {max_bytes // 2**20} MiB); not read"
    return None


def opencv_path_problem(path: str | os.PathLike[str]) -> str | None:
    """Why OpenCV cannot be given this path, or None.

    OpenCV's Python bindings crash the process (a segmentation fault) on a ``str`` that is not valid
    UTF-8, which is how Python spells a file name with bytes that are not UTF-8 (``surrogateescape``).
    """
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        return "the file name is not UTF-8 text, which OpenCV cannot open; rename the file"
    return None


def filestorage_nesting_problem(data: bytes, path: Path) -> str | None:
    """Why ``data`` (a file's bytes) must not reach ``cv2.FileStorage``, or None.

    Counts flow brackets and XML tags, and runs of block indentation or ``-`` indicators, which bound
    how deep the parser would recurse. A ``.gz`` file (FileStorage decompresses it) is checked
    decompressed, up to 64 MB.
    """
    if path.suffix.lower() == ".gz":
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(data)) as stream:
                data = stream.read(_MAX_DECOMPRESSED + 1)
        except (OSError, EOFError) as err:
            return f"not a readable gzip file ({err})"
        if len(data) > _MAX_DECOMPRESSED:
            return f"decompresses to more than {_MAX_DECOMPRESSED // 2**20} MB"
    depth = deepest = 0
    for match in _OPENERS.finditer(data):
        if match.group() in (b"]", b"}", b"</", b"/>"):
            depth = max(depth - 1, 0)
        else:
            depth += 1
            deepest = max(deepest, depth)
    if deepest > MAX_NESTING or re.search(rb"[ \t?-]{%d,}" % MAX_NESTING, data):
        return f"nested or indented more than {MAX_NESTING} levels deep"
    return None


def _check_file_bytes(path: Path) -> bytes:
    """The bytes of a camera file, refused (before OpenCV parses it) when it is not a small text file:
    missing, not a regular file, too large (not read; a file that begins as JSON may be larger, up to
    ``MAX_JSON_BYTES``), empty, binary, an XML document with a DOCTYPE (entity declarations: OpenCV's
    parser does not expand them, and a "billion laughs" file is a hostile one), or nested deeper than
    OpenCV's recursive parsers survive."""
    where = f"camera file {printable(path)}"
    limit = MAX_JSON_BYTES if _begins_as_json(path) else MAX_FILE_BYTES
    problem = input_file_problem(path, limit) or opencv_path_problem(path)
    if problem is not None:
        raise CameraError(f"{where}: {problem}")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise CameraError(f"{where}: cannot read ({err.strerror})") from err
    if not data.strip():
        raise CameraError(f"{where}: file is empty")
    if path.suffix.lower() != ".gz" and b"\0" in data:
        raise CameraError(f"{where}: binary data, not a camera file (a text file; {FORMATS_READ})")
    if re.search(rb"<!(DOCTYPE|ENTITY)", data[:65536], re.IGNORECASE):
        raise CameraError(f"{where}: XML with a DOCTYPE or entity declarations is not a camera file OpenCV reads")
    problem = filestorage_nesting_problem(data, path)
    if problem is not None:
        raise CameraError(f"{where}: not a camera file ({problem})")
    return data


def _begins_as_json(path: Path) -> bool:
    """Does the file at ``path`` begin with ``{`` (after a byte-order mark and white space)? False when it
    cannot be read (the checks that follow say why)."""
    if path.suffix.lower() == ".gz":
        return False
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # (opening a FIFO would wait for a writer: never opened here)
            return False
        with open(path, "rb") as file:
            head = file.read(4096)
    except (OSError, ValueError):
        return False
    return head.removeprefix(b"\xef\xbb\xbf").lstrip().startswith(b"{")


def _photonvision_document(data: bytes, path: Path) -> dict | None:
    """The parsed JSON object of a PhotonVision calibration (or camera settings) file, None for anything else
    (OpenCV's FileStorage JSON included: FileStorage reads it)."""
    if path.suffix.lower() == ".gz" or not data.removeprefix(b"\xef\xbb\xbf").lstrip().startswith(b"{"):
        return None
    try:
        document = json.loads(data.decode("utf-8-sig"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None  # (FileStorage then says what is wrong with it)
    if not isinstance(document, dict):
        return None
    if "cameraIntrinsics" in document or ("calibrations" in document and "camera_matrix" not in document):
        return document
    return None


def _one_photonvision_calibration(calibrations: object, where: str) -> dict:
    """The one calibration of a PhotonVision camera settings file's ``calibrations``."""
    if not isinstance(calibrations, list) or not all(isinstance(c, dict) for c in calibrations):
        raise CameraError(f"{where}: 'calibrations' must be a list of calibrations")
    if not calibrations:
        raise CameraError(f"{where}: holds no calibration ('calibrations' is empty): calibrate in PhotonVision first")
    if len(calibrations) > 1:
        sizes = ", ".join(_resolution_text(c.get("resolution")) for c in calibrations)
        raise CameraError(
            f"{where}: holds {len(calibrations)} calibrations ({sizes}): export the one of the resolution you "
            "track at from PhotonVision's calibration page and give that file"
        )
    return calibrations[0]


def _resolution_text(resolution: object) -> str:
    if isinstance(resolution, dict) and _is_number(resolution.get("width")) and _is_number(resolution.get("height")):
        return f"{resolution['width']:g}x{resolution['height']:g}"
    return "?"


def _is_number(value: object) -> bool:
    """A JSON number that is a finite float (an integer too large for one is not)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _photonvision_resolution(resolution: object, where: str) -> tuple[int, int]:
    """``resolution``: {"width": 1280.0, "height": 800.0} (OpenCV's Size, as PhotonVision writes it)."""
    if not isinstance(resolution, dict):
        raise CameraError(f'{where}: missing \'resolution\' ({{"width": W, "height": H}}, the calibrated image size)')
    size = []
    for key in ("width", "height"):
        value = resolution.get(key)
        if not _is_number(value) or value != int(value) or value <= 0:
            raise CameraError(f"{where}: 'resolution' {key} must be a positive integer, got {printable(value)}")
        size.append(int(value))
    return size[0], size[1]


def _photonvision_mat(document: dict, key: str, where: str) -> np.ndarray:
    """A matrix as PhotonVision writes it: {"rows": R, "cols": C, "type": 6, "data": [R x C numbers]}."""
    node = document.get(key)
    if node is None:
        raise CameraError(f"{where}: missing '{key}'")
    if not isinstance(node, dict):
        raise CameraError(f'{where}: \'{key}\' must be a matrix: {{"rows", "cols", "data"}}')
    rows, cols, data = node.get("rows"), node.get("cols"), node.get("data")
    counts = all(isinstance(n, int) and not isinstance(n, bool) and 0 < n <= 16 for n in (rows, cols))
    if not (counts and isinstance(data, list)):
        raise CameraError(f"{where}: '{key}' needs rows and cols (1 to 16) and a data list")
    if not all(_is_number(value) for value in data):
        raise CameraError(f"{where}: '{key}' data must hold finite numbers only")
    if len(data) != rows * cols:
        raise CameraError(f"{where}: '{key}' is {rows}x{cols} but has {len(data)} values")
    return np.asarray(data, dtype=np.float64).reshape(rows, cols)


def _parse_error(err: Exception) -> str:
    """The parser's own complaint, without OpenCV's source location and the file's name: OpenCV 5's
    binding raises ``SystemError("... returned a result with an exception set")`` with the
    ``cv2.error`` as its cause."""
    cause = err.__cause__ or err.__context__ if isinstance(err, SystemError) else err
    text = _first_line(cause if isinstance(cause, Exception) else err)
    found = re.search(r"\((\d+)\): (.*?)'?$", text)
    if found:
        return f"line {found.group(1)}: {found.group(2)}"
    return "unreadable" if "returned a result with an exception set" in text else printable(text)


def _first_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


def _read_mat(storage: cv2.FileStorage, key: str, path: Path, *, required: bool) -> np.ndarray | None:
    node = storage.getNode(key)
    if node.empty() or node.isNone():
        if required:
            raise CameraError(f"camera file {printable(path)}: missing '{key}'")
        return None
    if node.isSeq():
        return _read_numbers(node, key, path)
    if not node.isMap():
        raise CameraError(f"camera file {printable(path)}: '{key}' is not an OpenCV matrix (!!opencv-matrix)")
    # Read here rather than with FileNode.mat(): OpenCV 5 copies `data` into a matrix of `rows` x `cols`
    # before it checks the two agree, so a matrix without `cols` (0) overflows the heap and aborts later.
    rows, cols, data, dt = (node.getNode(name) for name in ("rows", "cols", "data", "dt"))
    if not (rows.isInt() and cols.isInt() and data.isSeq() and rows.real() > 0 and cols.real() > 0):
        raise CameraError(
            f"camera file {printable(path)}: '{key}' needs positive integer rows and cols and a data list"
        )
    if not (dt.empty() or dt.isNone()):  # OpenCV's !!opencv-matrix; ROS camera_info has no dt
        if not (dt.isString() and _ONE_CHANNEL_DT.fullmatch(dt.string())):
            raise CameraError(f"camera file {printable(path)}: '{key}' dt must be a one-channel element type such as d")
    values = _read_numbers(data, key, path)
    if values.size != rows.real() * cols.real():
        raise CameraError(
            f"camera file {printable(path)}: '{key}' is {int(rows.real())}x{int(cols.real())} "
            f"but has {values.size} values"
        )
    return values.reshape(int(rows.real()), int(cols.real()))


def _read_numbers(node: cv2.FileNode, key: str, path: Path) -> np.ndarray:
    """A sequence of numbers (OpenCV reads any other node as 0 or DBL_MAX: refuse them)."""
    items = [node.at(i) for i in range(node.size())]
    if not all(item.isInt() or item.isReal() for item in items):
        raise CameraError(f"camera file {printable(path)}: '{key}' must hold numbers only")
    return np.asarray([item.real() for item in items], dtype=np.float64)


def _read_int(storage: cv2.FileStorage, key: str, path: Path) -> int:
    node = storage.getNode(key)
    if node.empty() or node.isNone():
        raise CameraError(f"camera file {printable(path)}: missing '{key}'")
    if not (node.isInt() or node.isReal()):
        raise CameraError(f"camera file {printable(path)}: '{key}' must be a number")
    value = node.real()
    if not np.isfinite(value) or value != int(value) or value <= 0:
        raise CameraError(f"camera file {printable(path)}: '{key}' must be a positive integer, got {value:g}")
    return int(value)


@dataclass(frozen=True)
class CameraFile:
    """A camera file's values as read, before :class:`~ar_anchor.camera.CameraModel` checks them; ``where``
    names the file (and its format) for messages."""

    where: str
    matrix: np.ndarray | None
    dist: np.ndarray
    width: int
    height: int
    photonvision: bool = False


def read_camera_file(path: Path) -> CameraFile:
    """Read a camera file (OpenCV FileStorage YAML, XML or JSON; ROS camera_info YAML; PhotonVision calibration
    JSON); raise :class:`CameraError` naming the file and what is wrong with it."""
    data = _check_file_bytes(path)
    document = _photonvision_document(data, path)
    if document is not None:
        return _read_photonvision(document, path)
    if len(data) > MAX_FILE_BYTES:  # (a larger JSON file was let through to be read as PhotonVision's)
        raise CameraError(
            f"camera file {printable(path)}: is {len(data) / 2**20:.0f} MiB, too large to be one "
            f"(at most {MAX_FILE_BYTES // 2**20} MiB); not read"
        )
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # OpenCV 5's binding wraps parse errors in SystemError
        where = f"camera file {printable(path)}"
        raise CameraError(f"{where}: not valid OpenCV YAML/XML/JSON ({_parse_error(err)})") from None
    try:
        return _read_filestorage(storage, path)
    except (cv2.error, SystemError) as err:
        raise CameraError(f"camera file {printable(path)}: unreadable content ({_parse_error(err)})") from None
    except UnicodeDecodeError:  # a text value (dt, distortion_model) that is not UTF-8
        raise CameraError(f"camera file {printable(path)}: not UTF-8 text") from None
    finally:
        storage.release()


def _read_filestorage(storage: cv2.FileStorage, path: Path) -> CameraFile:
    """An opened OpenCV (or ROS camera_info) camera file's values."""
    if not storage.isOpened():
        raise CameraError(f"camera file {printable(path)}: cannot be parsed as OpenCV FileStorage ({FORMATS_READ})")
    if not storage.root().isMap():
        raise CameraError(f"camera file {printable(path)}: expected key: value pairs at the top level")
    if storage.getNode("camera_matrix").empty():
        raise CameraError(f"camera file {printable(path)}: missing 'camera_matrix', not a camera file ({FORMATS_READ})")
    matrix = _read_mat(storage, "camera_matrix", path, required=True)
    dist = _read_mat(storage, "distortion_coefficients", path, required=False)
    width = _read_int(storage, "image_width", path)
    height = _read_int(storage, "image_height", path)
    model = storage.getNode("distortion_model")  # ROS camera_info
    if not model.empty() and not model.isNone():
        name = model.string() if model.isString() else ""
        if name not in _ROS_DISTORTION_MODELS:
            raise CameraError(
                f"camera file {printable(path)}: distortion_model {name or '(not a name)'!r} is not supported "
                f"(use {' or '.join(_ROS_DISTORTION_MODELS)}: OpenCV's pinhole model)"
            )
    if matrix is not None and matrix.size == 9:
        matrix = matrix.reshape(3, 3)
    return CameraFile(f"camera file {printable(path)}", matrix, np.zeros(0) if dist is None else dist, width, height)


def _read_photonvision(document: dict, path: Path) -> CameraFile:
    """The values of a PhotonVision calibration (``document``, parsed from ``path``); :class:`CameraError`
    naming the file and the field at fault."""
    where = f"camera file {printable(path)} (PhotonVision calibration JSON)"
    if "cameraIntrinsics" not in document:  # a camera's settings file: its calibrations, one per resolution
        document = _one_photonvision_calibration(document.get("calibrations"), where)
    lens = document.get("lensmodel")
    if lens is not None and lens != _PHOTONVISION_LENS:
        raise CameraError(
            f"{where}: lensmodel {printable(lens)!r} is not supported (only {_PHOTONVISION_LENS}: OpenCV's pinhole "
            "model; recalibrate in PhotonVision with the OpenCV model)"
        )
    if document.get("isFisheye") is True:
        raise CameraError(f"{where}: a fisheye calibration (isFisheye) is not supported: OpenCV's pinhole model only")
    width, height = _photonvision_resolution(document.get("resolution"), where)
    matrix = _photonvision_mat(document, "cameraIntrinsics", where)
    dist_key = "distCoeffs" if "distCoeffs" in document else "cameraExtrinsics"  # (PhotonVision's older name)
    dist = _photonvision_mat(document, dist_key, where) if dist_key in document else np.zeros(0)
    if matrix.size == 9:
        matrix = matrix.reshape(3, 3)
    return CameraFile(where, matrix, dist.reshape(-1), width, height, photonvision=True)
