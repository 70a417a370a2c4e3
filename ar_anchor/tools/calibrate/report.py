"""What a calibration run leaves behind: the camera YAML (written atomically, read back before it
replaces anything) and the terminal report (views, intrinsics, distortion, errors, coverage)."""

from __future__ import annotations

import datetime as _dt
import math
import os
from pathlib import Path

import cv2
import numpy as np

from ...camera import CameraModel
from ...errors import InputError, OutputError
from .solve import CalibrationReport
from .views import reason_counts

__all__ = ["format_report", "write_camera_yaml"]


def write_camera_yaml(path: str | os.PathLike[str], report: CalibrationReport) -> None:
    """Write the camera YAML atomically (temporary file beside it, read back, then renamed)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"--out {path}: is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"--out {path}: cannot create its folder ({err.strerror})") from None
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp.yml")
    result = report.result
    try:
        try:
            report.camera.to_yaml(
                temporary,
                rms=float(result.rms),
                date=_dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                board=report.spec.describe(),
                views=len(result.views),
                coverage=round(report.coverage.fraction, 4),
                model=result.model,
                **_uncertainty_keys(report),
            )
        except (cv2.error, SystemError, OSError) as err:
            raise OutputError(f"--out {path}: cannot write ({_first_line(err)})") from None
        if not temporary.is_file():
            raise OutputError(f"--out {path}: cannot write")
        try:
            CameraModel.from_yaml(temporary)
        except InputError as err:  # our own file must read back
            raise OutputError(f"--out {path}: written file does not read back ({err})") from None
        try:
            os.replace(temporary, path)
        except OSError as err:
            raise OutputError(f"--out {path}: cannot write ({err.strerror})") from None
    finally:
        if temporary.exists():
            temporary.unlink(missing_ok=True)


def _uncertainty_keys(report: CalibrationReport) -> dict[str, str | np.ndarray]:
    """The camera file's uncertainty: ``std_intrinsics`` (fx fy cx cy k1 k2 p1 p2 k3, one standard
    deviation, NaN for a parameter held fixed; OpenCV's ``stdDeviationsIntrinsics`` order) and how it
    was estimated."""
    uncertainty = report.uncertainty
    std = uncertainty.std if uncertainty is not None else report.result.std
    keys: dict[str, str | np.ndarray] = {"std_intrinsics": np.array(std, np.float64).reshape(1, -1)}
    keys["std_intrinsics_method"] = (
        uncertainty.describe() if uncertainty is not None else "OpenCV's estimate from the residuals"
    )
    if uncertainty is not None and uncertainty.distrust:
        keys["std_intrinsics_unreliable"] = "; ".join(uncertainty.distrust)
    return keys


def _first_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


def format_report(report: CalibrationReport) -> str:
    """The terminal report: views, intrinsics, distortion, errors, coverage, warnings."""
    result = report.result
    camera = report.camera
    k = camera.camera_matrix
    uncertainty = report.uncertainty
    std = uncertainty.std if uncertainty is not None else result.std
    rejected = report.all_rejections
    lines = [
        f"calibrate {report.source}: {report.considered} view(s) considered"
        + (f" (one frame in {report.frame_step})" if report.frame_step > 1 else "")
        + f", {len(result.views)} used, {len(rejected)} rejected"
        + (f" ({reason_counts(rejected)})" if rejected else ""),
    ]
    shown = [r for r in rejected if r.reason != "no board" or len(rejected) <= 12]
    for rejection in shown[:12]:
        lines.append(f"  rejected {rejection}")
    if len(shown) > 12:
        lines.append(f"  ... and {len(shown) - 12} more")
    elif len(shown) < len(rejected):
        lines.append(f"  ... and {len(rejected) - len(shown)} view(s) without the board")

    def pm(value: float, sigma: float, digits: int) -> str:
        return f"{value:.{digits}f}" + (f" +-{sigma:.{digits}f}" if math.isfinite(sigma) else "")

    lines.append(
        f"camera {camera.width}x{camera.height}: fx {pm(k[0, 0], std[0], 2)}  fy {pm(k[1, 1], std[1], 2)}  "
        f"cx {pm(k[0, 2], std[2], 2)}  cy {pm(k[1, 2], std[3], 2)} px"
    )
    names = ("k1", "k2", "p1", "p2", "k3")
    dist = camera.dist_coeffs
    lines.append(
        "distortion "
        + "  ".join(f"{n} {dist[i]:+.5f}" for i, n in enumerate(names) if i < dist.size)
        + f"  ({result.model})"
    )
    opencv = result.std
    lines.append(
        "  +- is one standard deviation: "
        + (uncertainty.describe(timed=True) if uncertainty is not None else "OpenCV's estimate from the residuals")
        + (
            f" (OpenCV's alone: fx +-{opencv[0]:.2f} fy +-{opencv[1]:.2f} px)"
            if uncertainty is not None and uncertainty.ran > uncertainty.failed + 1
            else ""
        )
    )
    errors = np.asarray(result.errors_px)
    worst = int(np.argmax(errors))
    lines.append(
        f"RMS {result.rms:.3f} px"
        + (f" (first fit {result.first_rms:.3f} px on {len(result.first_views)} views)" if result.dropped else "")
        + f"; per view median {np.median(errors):.3f}, max {errors[worst]:.3f} ({result.views[worst].name})"
    )
    per_view = [f"{e:.2f}" for e in errors]
    for start in range(0, len(per_view), 16):
        lines.append(("  per-view px: " if start == 0 else "               ") + " ".join(per_view[start : start + 16]))
    coverage = report.coverage
    rows, cols = coverage.counts.shape
    lines.append(
        f"coverage {np.count_nonzero(coverage.counts)}/{coverage.counts.size} cells ({coverage.fraction:.0%}) "
        f"of a {cols}x{rows} grid, corners per cell:"
    )
    lines.extend("  " + line for line in coverage.heat_map().splitlines())
    for warning in report.warnings:
        lines.append(f"warning: {warning}")
    lines.append(f"({report.seconds:.1f} s)")
    return "\n".join(lines)
