"""`ar-anchor bench NAME`: the benchmarks, each writing NAME.md and NAME.json."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..errors import EXIT_OK, InputError
from .options import add_command, add_marker_length, int_at_least, load_tracker_config, non_negative_float


def _clip_list(text: str) -> tuple[str, ...]:
    """``--clips``: comma-separated names (checked against the benchmark's own list once it is known)."""
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated clip names, got {text!r}")
    return names


def add_parser(commands: Any) -> None:
    """The ``bench`` command's options."""
    bench = add_command(
        commands,
        "bench",
        "benchmarks on synthetic ground truth (and real video without it: real)",
        "stability: raw per-frame IPPE vs. the tracker over a grid of synthetic scenarios "
        "(flips, errors, jitter, lag, time to commit), written as markdown and JSON.",
    )
    bench.add_argument(
        "name",
        choices=("stability", "boards", "overlay", "speed", "run", "real", "profile", "offline", "batch", "groups"),
        help="stability: raw vs tracker; boards: lone marker vs a board; overlay: drawing cost vs triangles; "
        "speed: the speed targets, each a row with its target and pass/fail: chessboard.avi looped, 720p "
        "50 markers, 1080p one marker (replay processes vs a plain OpenCV SUBPIX + IPPE loop, taking turns), "
        "start-up, --help, live latency (--stages: per-stage times and accuracy of the tracker vs plain "
        "OpenCV loops in one process); "
        "run: ar-anchor replay fps, live latency and memory over a long live run, at 1080p; "
        "real: relative-pose consistency of markers on one rigid sheet in a real video (tracker, its raw "
        "per-frame pick, plain OpenCV), default chessboard.avi from $AR_ANCHOR_REALDATA; profile: the tracker's CPU "
        "per stage and its costliest functions (cProfile) on a real video (the same --video options as real); "
        "offline: the offline replay against --causal (time, memory over a long clip, chessboard.avi scores); "
        "batch: 12 synthetic clips replayed in a loop of ar-anchor replay vs ar-anchor batch (local, --ray); "
        "groups: each marker of a hand-held sheet alone vs its learned rigid group (wrong frames, jitter)",
    )
    _add_real_options(bench)
    bench.add_argument("--quick", action="store_true", help="half the scenarios, shorter clips")
    bench.add_argument(
        "--minutes",
        type=non_negative_float,
        default=None,
        help="run: length of the live run whose memory is watched (default 10; 0: skip; --quick: 0); "
        "offline: length of the synthetic clip (default 10; 0: skip; --quick: 1)",
    )
    bench.add_argument(
        "--clips",
        type=_clip_list,
        default=None,
        help="speed: only these parts, comma-separated, of chessboard,50markers,1080p,startup,live (default: "
        "all; --stages: clips of one,eight,board (every size),50markers,chessboard); run: of "
        "1080p,live,chessboard,50markers (default: all)",
    )
    bench.add_argument(
        "--frames",
        type=int_at_least(1),
        default=None,
        help="speed: frames of the synthetic clips (default 300 at 720p, 800 at 1080p; --quick 60, 120; "
        "--stages: per synthetic clip, chessboard.avi at most this, default 300, --quick 90); "
        "run: frames of the encoded 1080p and 50-marker clips (default 600; --quick 150); "
        "batch: frames per clip (default 300; --quick 60)",
    )
    bench.add_argument(
        "--repeats",
        type=int_at_least(1),
        default=None,
        help="speed: rounds of runs taking turns, medians over them (default 3; --quick 1)",
    )
    bench.add_argument(
        "--stages",
        action="store_true",
        help="speed: the per-stage comparison in one process (speed_stages.md) instead of the acceptance",
    )
    bench.add_argument("--config", type=Path, default=None, help="tracker TOML (default: configs/default.toml values)")
    bench.add_argument(
        "--out", type=Path, default=Path("bench") / "results", help="output directory (default bench/results)"
    )
    bench.set_defaults(func=cmd_bench)


def _add_real_options(bench: argparse.ArgumentParser) -> None:
    """``bench real`` (and ``profile``)'s inputs: the video, its calibration, dictionary, marker length, layout."""
    bench.add_argument("--video", type=Path, default=None, help="real: the video (default: chessboard.avi)")
    bench.add_argument(
        "--camera", type=Path, default=None, help="real: its calibration (default: camera.yml or intrinsics.yml by it)"
    )
    bench.add_argument("--dictionary", default=None, help="real: override [detector] dictionary")
    add_marker_length(bench, "real: override [markers] length_m, e.g. 50mm (a bare number is metres)")
    bench.add_argument(
        "--layout", type=Path, default=None, help="real: printed marker map (ArUco YAML or TOML): also score vs. it"
    )


def cmd_bench(args: argparse.Namespace) -> int:
    """``ar-anchor bench NAME``: run one benchmark, write ``NAME.md`` and ``NAME.json`` to ``--out``; the exit code."""
    from ..bench.boards import write_board_report
    from ..bench.overlay import write_overlay_report
    from ..bench.stability import write_stability_report
    from ..config import load_config
    from ..run.outputs import prepare_out_dir

    config = load_config(args.config)
    real = None
    if args.name in ("real", "profile"):  # their data files are checked (exit 2) before anything is written
        from ..bench.real import real_inputs

        real = real_inputs(args.video, args.camera, args.dictionary, args.marker_length, args.layout)
    clips = _checked_clips(args)  # exit 2 before anything is written
    prepare_out_dir(args.out)  # before minutes of work, not after
    command = _command(args)

    def progress(i: int, total: int, name: str) -> None:
        if not args.quiet:
            print(f"[{i + 1}/{total}] {name}", file=sys.stderr, flush=True)

    if args.name == "profile":
        _profile(args, real, command)
    elif real is not None:
        _real(args, real, command, progress)
    elif args.name == "run":
        from ..bench.run import write_run_report

        if args.minutes is not None:
            command += f" --minutes {args.minutes:g}"
        write_run_report(
            args.out,
            quick=args.quick,
            minutes=args.minutes,
            progress=progress,
            command=command,
            parts=clips,
            frames=args.frames,
        )
    elif args.name == "offline":
        from ..bench.offline import write_offline_report

        if args.minutes is not None:
            command += f" --minutes {args.minutes:g}"
        write_offline_report(args.out, quick=args.quick, minutes=args.minutes, progress=progress, command=command)
    elif args.name == "batch":
        from ..bench.batch import write_batch_report

        write_batch_report(args.out, quick=args.quick, frames=args.frames, progress=progress, command=command)
    elif args.name == "groups":
        from ..bench.groups import write_groups_report

        write_groups_report(args.out, quick=args.quick, progress=progress, command=command, config=config)
    elif args.name == "speed":
        results = _speed(args, clips, progress, command)
        for note in (results or {}).get("notes", []):  # (None from a stubbed writer)
            print(f"note: {note}", file=sys.stderr)
    elif args.name == "overlay":
        write_overlay_report(args.out, frames=30 if args.quick else 60, progress=progress, command=command)
    elif args.name == "boards":
        frames = 60 if args.quick else 150
        write_board_report(args.out, config=config, frames=frames, progress=progress, command=command)
    else:
        write_stability_report(args.out, quick=args.quick, config=config, progress=progress, command=command)
    name = "speed_stages" if args.name == "speed" and args.stages else args.name
    print(f"results: {args.out / (name + '.md')} and {args.out / (name + '.json')}")
    return EXIT_OK


def _real(args: argparse.Namespace, real: Any, command: str, progress: Any) -> None:
    """``bench real``: the real video tracked and scored, its report written and summarised."""
    from ..bench.real import real_summary, write_real_report

    for option in ("video", "camera", "dictionary", "marker_length", "layout", "config"):
        if getattr(args, option) is not None:
            command += f" --{option.replace('_', '-')} {getattr(args, option)}"
    config = load_tracker_config(  # as ar-anchor replay builds it
        argparse.Namespace(config=args.config, dictionary=real.dictionary, marker_length=real.marker_length_m)
    )

    video_name = real.video.name

    def frames(done: int, total: int | None) -> None:
        if done % 50 == 0 or done == total:
            progress(done - 1, total or done, f"frames of {video_name}")

    print(real_summary(write_real_report(args.out, real, config, command=command, progress=frames)))


def _speed(args: argparse.Namespace, clips: Any, progress: Any, command: str) -> Any:
    """``bench speed``: the acceptance (``clips``: its parts) or, with ``--stages``, the per-stage comparison
    (``clips``: its scenes and extra clips); the results."""
    if not args.stages:
        from ..bench.speed import write_speed_report

        return write_speed_report(
            args.out,
            quick=args.quick,
            progress=progress,
            command=command,
            frames=args.frames,
            repeats=args.repeats,
            **({"parts": clips} if clips is not None else {}),
        )
    from ..bench.speed import write_stages_report

    scenes, extra = clips if clips is not None else (None, None)
    return write_stages_report(
        args.out,
        quick=args.quick,
        progress=progress,
        command=command,
        frames=args.frames,
        **({"scenes": scenes, "extra": extra} if clips is not None else {}),
    )


def _command(args: argparse.Namespace) -> str:
    """The command line the report quotes (the options that change what is measured)."""
    command = f"ar-anchor bench {args.name}" + (" --stages" if args.name == "speed" and args.stages else "")
    command += " --quick" if args.quick else ""
    if args.clips is not None:
        command += " --clips " + ",".join(args.clips)
    if args.frames is not None:
        command += f" --frames {args.frames}"
    if args.repeats is not None:
        command += f" --repeats {args.repeats}"
    return command


def _profile(args: argparse.Namespace, real: Any, command: str) -> None:
    """``bench profile``: the tracker (configured as ``ar-anchor replay`` would be) profiled on the video."""
    from ..bench.profile import profile_tracker, write_profile_report

    config = load_tracker_config(
        argparse.Namespace(config=args.config, dictionary=real.dictionary, marker_length=real.marker_length_m)
    )
    write_profile_report(profile_tracker(real, config, frames=args.frames), args.out, command)


def _checked_clips(args: argparse.Namespace) -> Any:
    """``--clips`` checked against the chosen benchmark's names: speed's (scenes, extra clips), run's parts,
    None when not given; :class:`InputError` (exit 2) for an unknown name or a benchmark without clips."""
    if args.name != "speed" and (args.stages or args.repeats is not None):
        raise InputError(
            f"{'--stages' if args.stages else '--repeats'}: only bench speed takes it, not bench {args.name}"
        )
    if args.name == "speed" and args.stages and args.repeats is not None:
        raise InputError("--repeats: bench speed --stages does not take it")
    if args.clips is None and args.frames is None:
        return None
    if args.name == "profile" and args.clips is None:
        return None  # (--frames: the video's first frames only)
    if args.name == "batch" and args.clips is None:
        return None  # (--frames: frames per clip)
    if args.name not in ("speed", "run"):
        option = "--clips" if args.clips is not None else "--frames"
        raise InputError(f"{option}: only bench speed and bench run take it, not bench {args.name}")
    if args.clips is None:
        return None
    if args.name == "speed" and args.stages:
        from ..bench.speed import split_clips

        try:
            return split_clips(",".join(args.clips))
        except ValueError as err:
            raise InputError(f"--clips: {err}") from None
    if args.name == "speed":
        from ..bench.speed import PARTS

        unknown = [name for name in args.clips if name not in PARTS]
        if unknown:
            raise InputError(f"--clips: unknown part {unknown[0]!r} of bench speed (any of {','.join(PARTS)})")
        return tuple(name for name in PARTS if name in args.clips)
    from ..bench.run import RUN_PARTS

    unknown = [name for name in args.clips if name not in RUN_PARTS]
    if unknown:
        raise InputError(f"--clips: unknown part {unknown[0]!r} of bench run (any of {','.join(RUN_PARTS)})")
    return tuple(name for name in RUN_PARTS if name in args.clips)
