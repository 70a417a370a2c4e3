"""``ar-anchor map``: check the options, observe the inputs, solve the map, write the layout (YAML and
TOML), the report and the recording, print the summary and the board snippet."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager, suppress
from pathlib import Path

from ...camera import CameraModel
from ...config import ConfigValueError, implausible_length_hint
from ...config.dictionaries import canonical_dictionary
from ...errors import ConfigError, InputError, OutputError, SourceError, printable
from ...run.paths import Named, OutDirLock, check_paths, spec_inputs
from .model import frame_label
from .observe import Observed, observe_sources
from .recording import MapRecording
from .report import board_snippet, format_report, format_summary, write_layout_toml, write_layout_yaml
from .solve import build_map

__all__ = ["MapOutputs", "map_outputs", "run_map"]

log = logging.getLogger(__name__)

_YAML_SUFFIXES = (".yml", ".yaml")
_FEW_FRAMES = 10  # no marker in fewer searched frames than this, with --step or --max-frames: too few searched


class MapOutputs:
    """Where a map run writes: the YAML and TOML layouts, the report and the recording; ``primary`` is --out."""

    def __init__(self, out: Path, rrd: Path | None = None) -> None:
        suffix = out.suffix.lower()
        if suffix in _YAML_SUFFIXES:
            self.yaml, self.toml = out, out.with_suffix(".toml")
        elif suffix == ".toml":
            self.toml, self.yaml = out, out.with_suffix(".yml")
        else:
            raise InputError(
                f"--out {printable(out)}: give the layout file to write, ending in .yml (ArUco marker map) or .toml"
            )
        self.primary = out
        stem = out.with_suffix("")
        self.report = stem.with_name(stem.name + "_report.md")
        self.rrd = rrd if rrd is not None else out.with_suffix(".rrd")
        self.rrd_given = rrd is not None

    def option(self, path: Path) -> str:
        """The option that named ``path``: ``--rrd`` for a recording given by ``--rrd``, else ``--out``."""
        return "--rrd" if self.rrd_given and path == self.rrd else "--out"

    def folders(self) -> list[tuple[str, Path]]:
        """(option, folder) of each folder the outputs go in, once each (--out's first)."""
        found: list[tuple[str, Path]] = []
        for option, path in (("--out", self.primary), (self.option(self.rrd), self.rrd)):
            folder = path.parent
            if all(os.path.abspath(folder) != os.path.abspath(other) for _, other in found):
                found.append((option, folder))
        return found

    def named(self) -> list[tuple[str, Path]]:
        """(what, path) of every output, for messages and the report."""
        return [
            ("layout (ArUco marker map YAML)", self.yaml),
            ("layout (TOML)", self.toml),
            ("report", self.report),
            ("recording", self.rrd),
        ]


def map_outputs(out: Path, rrd: Path | None = None, inputs: Sequence[Named] = ()) -> MapOutputs:
    """The outputs of ``--out`` (and ``--rrd``), checked before any work and without creating anything (a
    failed run leaves no empty folder): not directories, not one another, not one of ``inputs`` (option,
    path), their folders creatable and writable, and no file but ``--out`` itself overwritten unless an
    earlier ``ar-anchor map`` wrote it. Each refusal names the option that gave the path."""
    outputs = MapOutputs(out, rrd)
    named = outputs.named()
    for what, path in named:
        option = outputs.option(path)
        if path.is_dir():
            raise InputError(f"{option} {printable(path)}: is a directory (the {what} is written there)")
        _check_folder(path, option)
    paths = [path.absolute() for _, path in named]
    if len(set(paths)) < len(paths):
        raise InputError(f"--rrd {printable(outputs.rrd)}: is one of the layout files --out writes")
    check_paths([(outputs.option(path), path) for _, path in named], inputs)
    ours = _written_by_map(outputs.report)
    for what, path in named:
        if path != outputs.primary and (path.exists() or path.is_symlink()) and not ours:
            option = outputs.option(path)
            given = path if option == "--rrd" else out
            raise InputError(
                f"{option} {printable(given)}: would overwrite {printable(path)} (its {what}), which ar-anchor map "
                f"did not write: move that file or give another {option}"
            )
    return outputs


def _check_folder(path: Path, option: str) -> None:
    """Can ``path``'s folder be created and written (its nearest existing ancestor a writable folder)?"""
    probe = path.parent.absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{option} {printable(path)}: {printable(probe)} is a file, not a folder")
    if not os.access(probe, os.W_OK):
        raise OutputError(f"{option} {printable(path)}: folder {printable(probe)} is not writable")


def _written_by_map(report: Path) -> bool:
    """Did an earlier ``ar-anchor map`` write these outputs (its report is there, with its title)?"""
    try:
        with report.open(encoding="utf-8", errors="replace") as handle:
            return handle.readline().startswith("# ar-anchor map")
    except OSError:
        return False


def _check_options(args: argparse.Namespace) -> None:
    """The marker length, dictionary (made canonical), --step and the inputs' existence (before anything is read)."""
    length = float(args.marker_length)
    hint = implausible_length_hint(length, "--marker-length")
    if hint is not None:
        raise InputError(hint)
    try:
        args.dictionary = canonical_dictionary(args.dictionary)  # tag36h11 in, DICT_APRILTAG_36H11 in the outputs
    except ConfigValueError as err:
        raise ConfigError(f"--dictionary: {err.problem}") from None
    for source in args.sources:
        text = str(source)
        if not any(ch in text for ch in "*?[") and not Path(text).exists():
            raise SourceError(f"{printable(text)}: not found (expected a video file, an image folder or a glob)")


@contextmanager
def _claimed(outputs: MapOutputs) -> Iterator[None]:
    """Create the outputs' folders and hold each one's lock (:class:`~ar_anchor.run.paths.OutDirLock`: one run per
    output folder, as for every command) until the block ends; folders this call created are removed again
    when the block fails (a failed run leaves none)."""
    created: list[Path] = []
    with ExitStack() as stack:
        try:
            for option, folder in outputs.folders():
                missing = []
                probe = folder
                while not probe.exists() and probe != probe.parent:
                    missing.append(probe)
                    probe = probe.parent
                try:
                    folder.mkdir(parents=True, exist_ok=True)
                except OSError as err:
                    raise OutputError(
                        f"{option} {printable(outputs.primary if option == '--out' else outputs.rrd)}: cannot create "
                        f"{printable(folder)} ({err.strerror or err})"
                    ) from None
                created += missing
                stack.enter_context(OutDirLock(folder, option))
            yield
        except BaseException:
            stack.close()  # the locks go first: then the folders are empty
            for folder in created:
                with suppress(OSError):
                    folder.rmdir()
            raise


def run_map(args: argparse.Namespace) -> int:
    """``ar-anchor map``: build the map, write its files, print the summary; the exit code."""
    quiet = bool(getattr(args, "quiet", False))
    _check_options(args)
    sources = [str(s) for s in args.sources]
    inputs = [("--camera", Path(args.camera))]
    for source in sources:
        inputs += spec_inputs(source, "VIDEO")
    outputs = map_outputs(Path(args.out), getattr(args, "rrd", None), inputs)
    camera = CameraModel.from_yaml(args.camera)
    with _claimed(outputs):
        return _run_map(args, outputs, sources, camera, quiet)


def _check_observed(observed: Observed, args: argparse.Namespace, shown: str) -> None:
    """A clear error when the sources gave no frame, no marker, or never two markers in one frame."""
    if observed.frames_considered == 0:
        raise SourceError(f"{shown}: no frame could be read")
    if not observed.markers_seen:
        few = observed.frames_considered < _FEW_FRAMES and (args.step > 1 or args.max_frames is not None)
        raise InputError(
            f"no marker of {args.dictionary} found in the {observed.frames_considered} frame(s) searched in {shown}: "
            + (
                "only that few frames were searched: a lower --step or a higher --max-frames?"
                if few
                else "wrong --dictionary? (the printed markers' family, e.g. DICT_4X4_50 or DICT_ARUCO_ORIGINAL)"
            )
        )
    if not observed.frames:
        seen = ", ".join(str(i) for i in sorted(observed.markers_seen)[:12])
        raise InputError(
            f"fewer than two markers were ever seen together in one frame of {shown} (ids seen: {seen}): a map needs "
            "frames showing two markers or more"
        )


def _run_map(
    args: argparse.Namespace, outputs: MapOutputs, sources: list[str], camera: CameraModel, quiet: bool
) -> int:
    def progress(message: str) -> None:
        if not quiet:
            print(f"ar-anchor: {message}", file=sys.stderr, flush=True)

    observed = observe_sources(
        sources,
        camera,
        args.dictionary,
        float(args.marker_length),
        step=args.step,
        max_frames=args.max_frames,
        progress=progress,
    )
    shown = ", ".join(printable(s) for s in sources)
    _check_observed(observed, args, shown)
    progress(
        f"{len(observed.frames)} frame(s) with two markers or more, ids {len(observed.markers_seen)}; solving the map"
    )
    solution = build_map(
        observed.frames,
        observed.cameras,
        float(args.marker_length),
        origin=getattr(args, "origin", None),
        progress=progress,
    )
    several = len(sources) > 1
    report = format_report(
        solution,
        sources=sources,
        dictionary=args.dictionary,
        frames_considered=observed.frames_considered,
        frames_read=observed.frames_read,
        step=args.step,
        outputs=outputs.named(),
        layout_name=outputs.primary.name,
        frame_label=lambda name: frame_label(name, several),
    )
    recording = MapRecording(outputs.rrd, spawn=bool(getattr(args, "spawn", False)))
    succeeded = False
    try:
        header = (
            f"ar-anchor map: {len(solution.map.ids)} markers of {args.dictionary}, "
            f"side {float(args.marker_length):g} m, from {shown}\n"
            f"map frame: marker {solution.map.reference_id}'s (centre, x right, y up, z out); metres"
        )
        write_layout_yaml(outputs.yaml, solution.map)
        write_layout_toml(outputs.toml, solution.map, header)
        try:
            outputs.report.write_text(report, encoding="utf-8")
        except OSError as err:
            raise OutputError(f"--out {printable(outputs.report)}: cannot write ({err.strerror})") from None
        recording.result(solution, report)
        succeeded = True
    finally:
        recording.close(keep=succeeded)
    for marker_id, why in solution.unplaced.items():
        log.warning("marker %d not mapped: %s", marker_id, why)
    print(f"map: {format_summary(solution)}")
    if not quiet:
        print("track it as one board with this tracker config (beside the layout):")
        print(board_snippet(outputs.primary.name, args.dictionary).rstrip("\n"))
    # the last line: every file written, what each is
    print("outputs: " + ", ".join(f"{printable(path)} ({what})" for what, path in outputs.named()))
    return 0
