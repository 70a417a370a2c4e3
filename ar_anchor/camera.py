"""Camera intrinsics: the pinhole matrix K, lens distortion and the image size they belong to.

Files are OpenCV FileStorage YAML (or XML, JSON) with the keys OpenCV's calibration sample writes:
``camera_matrix`` (3x3), ``distortion_coefficients`` (1xN, N in 4, 5, 8, 12, 14),
``image_width``, ``image_height``. ROS ``camera_info`` YAML (``camera_calibration``'s output) has the
same keys with ``rows``/``cols``/``data`` maps in place of ``!!opencv-matrix``; it is read too, for the
distortion models OpenCV's pinhole model is (``plumb_bob``, ``rational_polynomial``). PhotonVision's
calibration JSON (its calibration page's export: ``resolution`` {width, height}, ``cameraIntrinsics`` and
``distCoeffs`` as {rows, cols, type, data}; before 2024 the distortion was named ``cameraExtrinsics``) is
read for its OpenCV lens model (``lensmodel`` LENSMODEL_OPENCV, not fisheye), as is a PhotonVision camera
settings file holding one such calibration (``calibrations``).

Without any file, :meth:`CameraModel.assumed` is the pinhole a focal length (or a field of view) gives.
"""

from __future__ import annotations

import gzip
import io
import json
import logging
import math
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .errors import CameraError, OutputError, printable

__all__ = ["FORMATS_READ", "MAX_FILE_BYTES", "CameraModel", "input_file_problem"]

log = logging.getLogger(__name__)

_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
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

# A camera matrix that cannot be a real camera's is refused, one that is odd is used with a warning:
_FOCAL_RANGE = (0.01, 1000.0)  # fx, fy in image sides (max(width, height)): 179 deg to 0.06 deg of view
_CENTRE_SLACK = 0.5  # the principal point within [-0.5, 1.5] x the image size (warned outside the image)
_SKEW_REFUSED = 0.1  # |K[0][1]| above this x fx is refused (OpenCV's model has no skew and ignores it) ...
_SKEW_WARNED = 1e-6  # ... and above this x fx warned about


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


def focal_from_hfov(width: int, hfov_deg: float) -> float:
    """The focal length (pixels) of a pinhole whose ``width``-pixel image spans ``hfov_deg`` degrees across."""
    return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def hfov_from_focal(width: int, focal_px: float) -> float:
    """The horizontal field of view (degrees) of a pinhole of focal length ``focal_px`` (pixels), ``width`` wide."""
    return math.degrees(2.0 * math.atan2(width / 2.0, focal_px))


@dataclass(frozen=True)
class CameraModel:
    """Calibrated camera.

    Attributes
    ----------
    camera_matrix : (3, 3) float64, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels, with pixel
        centres at integer coordinates (OpenCV's convention).
    dist_coeffs : (N,) float64, OpenCV distortion (k1, k2, p1, p2[, k3[, ...]]); empty for none.
    width, height : image size in pixels the intrinsics were calibrated at.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        matrix = np.asarray(self.camera_matrix, dtype=np.float64)
        if matrix.shape != (3, 3):
            raise CameraError(f"camera_matrix: expected 3x3, got shape {matrix.shape}")
        if not np.all(np.isfinite(matrix)):
            raise CameraError("camera_matrix: contains non-finite values")
        fx, fy = matrix[0, 0], matrix[1, 1]
        if fx <= 0 or fy <= 0:
            raise CameraError(f"camera_matrix: focal lengths must be > 0, got fx={fx:g}, fy={fy:g}")
        if not np.allclose(matrix[2], [0.0, 0.0, 1.0]) or matrix[1, 0] != 0.0:
            raise CameraError("camera_matrix: last row must be [0, 0, 1] and K[1][0] must be 0")
        dist = np.asarray(self.dist_coeffs, dtype=np.float64).reshape(-1)
        if dist.size not in _DIST_LENGTHS:
            raise CameraError(f"distortion_coefficients: expected 4, 5, 8, 12 or 14 values (or none), got {dist.size}")
        if not np.all(np.isfinite(dist)):
            raise CameraError("distortion_coefficients: contains non-finite values")
        if not (isinstance(self.width, (int, np.integer)) and isinstance(self.height, (int, np.integer))):
            raise CameraError("image_width/image_height: must be integers")
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        matrix.flags.writeable = False
        dist.flags.writeable = False
        object.__setattr__(self, "camera_matrix", matrix)
        object.__setattr__(self, "dist_coeffs", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_fov(cls, width: int, height: int, fx: float, fy: float | None = None) -> CameraModel:
        """Ideal pinhole camera, principal point at the image centre ((W-1)/2, (H-1)/2)."""
        fy = fx if fy is None else fy
        matrix = np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(matrix, np.zeros(0), width, height)

    @classmethod
    def assumed(
        cls, width: int, height: int, *, focal_px: float | None = None, hfov_deg: float | None = None
    ) -> CameraModel:
        """The pinhole a camera without a calibration is taken for: principal point at the image centre, no
        distortion, fx = fy = ``focal_px``, or ``(width / 2) / tan(hfov_deg / 2)`` from the horizontal field of
        view ``hfov_deg`` (degrees) of a ``width`` x ``height`` image; exactly one of the two is given."""
        if (focal_px is None) == (hfov_deg is None):
            raise ValueError("give exactly one of focal_px and hfov_deg")
        if focal_px is None:
            focal_px = focal_from_hfov(width, hfov_deg)
        return cls.from_fov(width, height, float(focal_px))

    @classmethod
    def default_synthetic(cls) -> CameraModel:
        """The camera of ``configs/camera_synthetic.yml``: 1280x720, fx = fy = 1000 px, no distortion."""
        return cls.from_fov(1280, 720, 1000.0)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> CameraModel:
        """Read a camera file (OpenCV FileStorage YAML, XML or JSON; ROS camera_info YAML; PhotonVision calibration
        JSON); raise :class:`CameraError` naming the file."""
        path = Path(path)
        data = _check_file_bytes(path)
        document = _photonvision_document(data, path)
        if document is not None:
            return cls._from_photonvision(document, path)
        if len(data) > MAX_FILE_BYTES:  # (a larger JSON file was let through to be read as PhotonVision's)
            raise CameraError(
                f"camera file {printable(path)}: is {len(data) / 2**20:.0f} MiB, too large to be one "
                f"(at most {MAX_FILE_BYTES // 2**20} MiB); not read"
            )
        try:
            storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as err:  # OpenCV 5's binding wraps parse errors in SystemError
            raise CameraError(
                f"camera file {printable(path)}: not valid OpenCV YAML/XML/JSON ({_parse_error(err)})"
            ) from None
        try:
            if not storage.isOpened():
                raise CameraError(
                    f"camera file {printable(path)}: cannot be parsed as OpenCV FileStorage ({FORMATS_READ})"
                )
            if not storage.root().isMap():
                raise CameraError(f"camera file {printable(path)}: expected key: value pairs at the top level")
            if storage.getNode("camera_matrix").empty():
                raise CameraError(
                    f"camera file {printable(path)}: missing 'camera_matrix', not a camera file ({FORMATS_READ})"
                )
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
        except (cv2.error, SystemError) as err:
            raise CameraError(f"camera file {printable(path)}: unreadable content ({_parse_error(err)})") from None
        except UnicodeDecodeError:  # a text value (dt, distortion_model) that is not UTF-8
            raise CameraError(f"camera file {printable(path)}: not UTF-8 text") from None
        finally:
            storage.release()
        if matrix is not None and matrix.size == 9:
            matrix = matrix.reshape(3, 3)
        try:
            camera = cls(matrix, np.zeros(0) if dist is None else dist, width, height)
            camera.check_plausible()
        except CameraError as err:
            raise CameraError(f"camera file {printable(path)}: {err}") from err
        return camera

    @classmethod
    def _from_photonvision(cls, document: dict, path: Path) -> CameraModel:
        """The camera of a PhotonVision calibration (``document``, parsed from ``path``); :class:`CameraError`
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
            raise CameraError(
                f"{where}: a fisheye calibration (isFisheye) is not supported: OpenCV's pinhole model only"
            )
        width, height = _photonvision_resolution(document.get("resolution"), where)
        matrix = _photonvision_mat(document, "cameraIntrinsics", where)
        dist_key = "distCoeffs" if "distCoeffs" in document else "cameraExtrinsics"  # (PhotonVision's older name)
        dist = _photonvision_mat(document, dist_key, where) if dist_key in document else np.zeros(0)
        if matrix.size == 9:
            matrix = matrix.reshape(3, 3)
        try:
            camera = cls(matrix, dist.reshape(-1), width, height)
            camera.check_plausible()
        except CameraError as err:
            raise CameraError(f"{where}: {err}") from err
        log.info("%s: %dx%d, fx %.1f px", where, width, height, camera.camera_matrix[0, 0])
        return camera

    def to_yaml(self, path: str | os.PathLike[str], **extra: str | float | int | np.ndarray) -> None:
        """Write the OpenCV FileStorage YAML that :meth:`from_yaml` reads (extra scalars and matrices appended)."""
        problem = opencv_path_problem(path)
        if problem is not None:
            raise OutputError(f"{path}: cannot write ({problem})")
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        try:
            storage.write("image_width", self.width)
            storage.write("image_height", self.height)
            storage.write("camera_matrix", np.array(self.camera_matrix))
            dist = self.dist_coeffs if self.dist_coeffs.size else np.zeros(5)
            storage.write("distortion_coefficients", np.array(dist).reshape(1, -1))
            for key, value in extra.items():
                storage.write(key, value)
        finally:
            storage.release()

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    @property
    def has_distortion(self) -> bool:
        return bool(self.dist_coeffs.size and np.any(self.dist_coeffs != 0.0))

    @property
    def dist_or_none(self) -> np.ndarray | None:
        """Distortion for OpenCV calls (None when there is none)."""
        return self.dist_coeffs if self.has_distortion else None

    def check_plausible(self) -> None:
        """Refuse (:class:`CameraError`) intrinsics no real camera has, warn about odd ones.

        Refused: a focal length outside 0.01 to 1000 image sides (checked before anything is computed
        from it), a principal point far outside the image (beyond half an image size), a skew
        ``K[0][1]`` above a tenth of fx (OpenCV's model has no skew: it ignores it), and distortion
        that folds the image (the lens model turns back on itself before the image's edge, so that two
        directions land on one pixel). Warned: a principal point outside the image, a small skew.
        """
        k, (width, height) = self.camera_matrix, self.size
        fx, fy, skew, cx, cy = k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]
        low, high = (factor * max(width, height) for factor in _FOCAL_RANGE)
        for name, focal in (("fx", fx), ("fy", fy)):
            if not low <= focal <= high:
                raise CameraError(
                    f"camera_matrix: {name} = {focal:g} px is no focal length for a {width}x{height} image "
                    f"(expected {low:g} to {high:g} px)"
                )
        slack_x, slack_y = _CENTRE_SLACK * width, _CENTRE_SLACK * height
        centre = f"principal point (cx, cy) = ({cx:g}, {cy:g})"
        if not (-slack_x <= cx <= width + slack_x and -slack_y <= cy <= height + slack_y):
            raise CameraError(
                f"camera_matrix: {centre} lies far outside the {width}x{height} image (a mistyped value, or the "
                "calibration of another image size?)"
            )
        if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
            log.warning(
                "camera_matrix: %s lies outside the %dx%d image (a cropped image's calibration?)", centre, width, height
            )
        if abs(skew) > _SKEW_REFUSED * fx:
            raise CameraError(f"camera_matrix: skew K[0][1] = {skew:g}: OpenCV's camera model has none (expected 0)")
        if abs(skew) > _SKEW_WARNED * fx:
            log.warning("camera_matrix: skew K[0][1] = %g is ignored: OpenCV's camera model has none", skew)
        fold = _distortion_fold(self)
        if fold is not None:
            raise CameraError(
                f"distortion_coefficients fold the image: the lens model turns back on itself near pixel "
                f"({fold[0]:.0f}, {fold[1]:.0f}), inside the {width}x{height} image (not a usable calibration)"
            )

    def scaled_to(self, width: int, height: int, *, warn: bool = True) -> CameraModel:
        """Intrinsics for the same lens at another resolution (pixel-centre convention kept).

        Logs a warning (calibrate at the resolution you track at when you can). A different aspect
        ratio is a :class:`CameraError`: the stream is then cropped or stretched in a way the
        calibration cannot know.
        """
        if (width, height) == self.size:
            return self
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise CameraError(
                f"camera calibrated at {self.width}x{self.height} (aspect {self.width / self.height:.3f}) cannot be "
                f"used for {width}x{height} frames (aspect {width / height:.3f}): calibrate at this resolution"
            )
        log.log(
            logging.WARNING if warn else logging.DEBUG,
            "camera calibrated at %dx%d used at %dx%d: scaling intrinsics by %.4g",
            self.width,
            self.height,
            width,
            height,
            sx,
        )
        k = np.array(self.camera_matrix)
        k[0, 0] *= sx
        k[0, 1] *= sx
        k[1, 1] *= sy
        k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
        k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
        return CameraModel(k, self.dist_coeffs, width, height)

    def project(self, points_in_camera: np.ndarray) -> np.ndarray:
        """Project camera-frame points (N, 3) to pixels (N, 2) through the distortion model."""
        points = np.asarray(points_in_camera, dtype=np.float64).reshape(-1, 3)
        if points.size == 0:
            return np.zeros((0, 2))
        pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), self.camera_matrix, self.dist_or_none)
        return pixels.reshape(-1, 2)


def _distort(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of normalised image points (radial, rational, tangential, thin prism; the
    14-coefficient model's sensor tilt is left out: a projective map, it folds nothing)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return xd, yd


def _distortion_fold(camera: CameraModel, rays: int = 72, samples: int = 800) -> tuple[float, float] | None:
    """Where (pixels) the distortion model folds inside the image, or None when it does not.

    Walks ``rays`` directions out from the principal point, from a millionth of the focal length to ten
    focal lengths off-axis (84 deg), and looks at the Jacobian of the undistorted-to-distorted map: where
    its determinant is not positive the map folds. Only the part of each ray before its distorted point
    leaves the image counts (beyond it, a polynomial's turn is outside the calibrated field and harmless).
    """
    if not camera.has_distortion:
        return None
    d = np.zeros(14)
    d[: camera.dist_coeffs.size] = camera.dist_coeffs
    k, (width, height) = camera.camera_matrix, camera.size
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)[:, None]
    radii = np.geomspace(1e-6, 10.0, samples)[None, :]
    x, y = radii * np.cos(angles), radii * np.sin(angles)
    h = radii * 1e-5
    with np.errstate(all="ignore"):
        xd, yd = _distort(x, y, d)
        dx_x, dy_x = (a - b for a, b in zip(_distort(x + h, y, d), _distort(x - h, y, d)))
        dx_y, dy_y = (a - b for a, b in zip(_distort(x, y + h, d), _distort(x, y - h, d)))
        det = dx_x * dy_y - dx_y * dy_x
        u, v = fx * xd + cx, fy * yd + cy
        inside = (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
        folded = ~(det > 0) | ~np.isfinite(u) | ~np.isfinite(v)
    # each ray up to (not including) its first sample outside the image
    before_exit = np.cumprod(inside, axis=1).astype(bool)
    bad = folded & before_exit
    if not bad.any():
        return None
    ray, sample = np.argwhere(bad)[0]
    previous = max(sample - 1, 0)
    return float(u[ray, previous]), float(v[ray, previous])


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
