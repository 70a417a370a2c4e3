"""Annotated stills: the overlay frames of an image folder written back as images (``--images-out DIR``).

Each image of the source gets its annotated copy in ``DIR`` under the same file name, in the format its
extension says (``.png``, ``.jpg``, ...: OpenCV's encoders), the overlay drawn exactly as ``--video-out``
draws it. The rule of every command that writes holds (:mod:`ar_anchor.run.written`): a file of ``DIR`` the
command did not write is never replaced (``DIR/.ar-anchor-images-out.json`` lists the images it wrote), and
``DIR`` may not be the folder of the source images, which the copies would replace.

:func:`plan_images_out` checks all of that before the run writes anything (an :class:`InputError`, exit 2,
naming ``--images-out``); :class:`AnnotatedStillsWriter` then writes each image whole (into a temporary file
beside it, renamed into place), in the run's output thread.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, OutputError, printable
from .outputs import check_not_a_file, write_failure
from .written import WrittenFiles, refuse_theirs

__all__ = ["MANIFEST_COMMAND", "AnnotatedStillsWriter", "StillsPlan", "plan_images_out"]

MANIFEST_COMMAND = "images-out"  # DIR/.ar-anchor-images-out.json: the images --images-out wrote
_JPEG_QUALITY = 95


@dataclass(frozen=True)
class StillsPlan:
    """Where each frame's annotated image goes: ``folder`` and, by frame index, the file name in it."""

    folder: Path
    names: Mapping[int, str] = field(default_factory=dict)


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return Path(os.path.abspath(path))


def plan_images_out(folder: Path, files: Sequence[Path], option: str = "--images-out") -> StillsPlan:
    """The annotated copies of the source images ``files`` (frame ``i`` is ``files[i]``) in ``folder``,
    checked: ``folder`` is no file, not the source images' own folder, two images do not share a name, each
    extension has an encoder, and no file of those names is there that the command did not write."""
    import cv2

    if folder.exists() and not folder.is_dir():
        raise InputError(f"{option} {printable(folder)}: is a file, not a folder (give the folder to write into)")
    check_not_a_file(folder, option)  # (a file on the way: it can never be created)
    where = _resolved(folder)
    for file in files:
        if _resolved(Path(file)).parent == where:
            raise InputError(
                f"{option} {printable(folder)}: is the folder of the source images; the annotated copies "
                "would replace them (give another folder)"
            )
    names: dict[int, str] = {}
    first: dict[str, Path] = {}
    for index, file in enumerate(files):
        name = Path(file).name
        if name in first:
            raise InputError(
                f"{option} {printable(folder)}: two source images are named {printable(name)} "
                f"({printable(first[name])}, {printable(file)}); the copies keep the names: "
                "replay one folder at a time"
            )
        first[name] = Path(file)
        suffix = Path(name).suffix.lower()
        if not cv2.haveImageWriter(f"x{suffix}"):
            raise InputError(
                f"{option}: {printable(file)}: OpenCV cannot write {suffix or 'extension-less'} images (the "
                "copies keep the source's format: convert the sources to .png or .jpg)"
            )
        names[index] = name
    if folder.is_dir():
        theirs = WrittenFiles(folder, MANIFEST_COMMAND).theirs(names.values())
        refuse_theirs(folder, theirs, not_written_by="no ar-anchor --images-out wrote", writer="the run", option=option)
    return StillsPlan(folder, names)


class AnnotatedStillsWriter:
    """Writes the annotated image of each frame ``plan`` names, whole; :attr:`written` counts them."""

    def __init__(self, plan: StillsPlan) -> None:
        self.plan = plan
        self.written = 0
        try:
            plan.folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(
                f"--images-out {printable(plan.folder)}: cannot create the folder ({err.strerror or err})"
            ) from None
        self._manifest = WrittenFiles(plan.folder, MANIFEST_COMMAND)

    def wants(self, index: int) -> bool:
        """Does frame ``index`` get an annotated image?"""
        return index in self.plan.names

    def write(self, index: int, image: np.ndarray) -> None:
        """Encode ``image`` (BGR) in the format of frame ``index``'s file name and write it whole."""
        import cv2

        name = self.plan.names[index]
        path = self.plan.folder / name
        suffix = Path(name).suffix.lower()
        params = [cv2.IMWRITE_JPEG_QUALITY, _JPEG_QUALITY] if suffix in (".jpg", ".jpeg") else []
        if suffix == ".pgm":  # (grey only)
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        ok, data = cv2.imencode(suffix, image, params)
        if not ok:
            raise OutputError(f"{printable(path)}: OpenCV cannot encode the annotated image as {suffix}")
        temporary = path.with_name(f".{name}.ar-anchor.tmp")
        try:
            with open(temporary, "wb") as out:
                out.write(data.tobytes())
            os.replace(temporary, path)
        except OSError as err:
            temporary.unlink(missing_ok=True)
            raise write_failure(path, err) from None
        self._manifest.record(name)
        self.written += 1

    def close(self) -> None:
        """Save the list of the images written (so that a later run may replace them)."""
        self._manifest.save()
