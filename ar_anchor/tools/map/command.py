"""``ar-anchor map``: check the options, observe the inputs, solve the map, write the layout (YAML and
TOML), the report and the recording, print the summary and the board snippet."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ...camera import CameraModel
from ...config import ConfigValueError, implausible_length_hint
from ...config.dictionaries import dictionary_id
from ...errors import ConfigError, InputError, OutputError, SourceError, printable
from ...run.outputs import prepare_out_file_folder
from ...run.paths import check_paths, spec_inputs
from .observe import observe_sources
from .recording import MapRecording
from .report import board_snippet, format_report, format_summary, write_layout_toml, write_layout_yaml
from .solve import build_map

__all__ = ["MapOutputs", "map_outputs", "run_map"]

log = logging.getLogger(__name__)

_YAML_SUFFIXES = (".yml", ".yaml")


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

    def named(self) -> list[tuple[str, Path]]:
        """(what, path) of every output, for messages and the report."""
        return [
            ("layout (ArUco marker map YAML)", self.yaml),
            ("layout (TOML)", self.toml),
            ("report", self.report),
            ("recording", self.rrd),
        ]


def map_outputs(out: Path, rrd: Path | None = None) -> MapOutputs:
    """The outputs of ``--out`` (and ``--rrd``), checked: not directories, their folder writable."""
    outputs = MapOutputs(out, rrd)
    for what, path in outputs.named():
        option = "--rrd" if path == outputs.rrd and rrd is not None else "--out"
        if path.is_dir():
            raise InputError(f"{option} {printable(path)}: is a directory (the {what} is written there)")
    prepare_out_file_folder(out)
    return outputs


def _check_options(args: argparse.Namespace) -> None:
    """The marker length, dictionary, --step and the inputs' existence (before anything is read)."""
    length = float(args.marker_length)
    hint = implausible_length_hint(length, "--marker-length")
    if hint is not None:
        raise InputError(hint)
    try:
        dictionary_id(args.dictionary)
    except ConfigValueError as err:
        raise ConfigError(f"--dictionary: {err.problem}") from None
    for source in args.sources:
        text = str(source)
        if not any(ch in text for ch in "*?[") and not Path(text).exists():
            raise SourceError(f"{printable(text)}: not found (expected a video file, an image folder or a glob)")


def _frame_label(names: list[str], several: bool) -> dict[str, str]:
    out = {}
    for name in names:
        source, frame = name.split(":")
        out[name] = f"input {int(source) + 1} frame {frame}" if several else f"frame {frame}"
    return out


def run_map(args: argparse.Namespace) -> int:
    """``ar-anchor map``: build the map, write its files, print the summary; the exit code."""
    quiet = bool(getattr(args, "quiet", False))
    _check_options(args)
    outputs = map_outputs(Path(args.out), getattr(args, "rrd", None))
    sources = [str(s) for s in args.sources]
    camera = CameraModel.from_yaml(args.camera)
    inputs = [("--camera", Path(args.camera))]
    for source in sources:
        inputs += spec_inputs(source, "VIDEO")
    named = [("--rrd" if path == outputs.rrd else "--out", path) for _, path in outputs.named()]
    check_paths(named, inputs)

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
    if observed.frames_considered == 0:
        raise SourceError(f"{shown}: no frame could be read")
    if not observed.markers_seen:
        raise InputError(
            f"no marker of {args.dictionary} found in the {observed.frames_considered} frame(s) searched in {shown}: "
            "wrong --dictionary? (the printed markers' family, e.g. DICT_4X4_50 or DICT_ARUCO_ORIGINAL)"
        )
    if not observed.frames:
        seen = ", ".join(str(i) for i in sorted(observed.markers_seen)[:12])
        raise InputError(
            f"fewer than two markers were ever seen together in one frame of {shown} (ids seen: {seen}): a map needs "
            "frames showing two markers or more"
        )
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
    labels = _frame_label(solution.frame_order + [d[0] for d in solution.dropped], len(sources) > 1)
    report = format_report(
        solution,
        sources=sources,
        dictionary=args.dictionary,
        frames_considered=observed.frames_considered,
        frames_read=observed.frames_read,
        step=args.step,
        outputs=outputs.named(),
        layout_name=outputs.primary.name,
        frame_label=lambda name: labels.get(name, name),
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
    for what, path in outputs.named():
        print(f"  {what}: {printable(path)}")
    if not quiet:
        print("track it as one board with this tracker config (beside the layout):")
        print(board_snippet(outputs.primary.name, args.dictionary).rstrip("\n"))
    return 0
