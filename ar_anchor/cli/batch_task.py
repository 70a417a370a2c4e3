"""The task of ``ar-anchor batch`` (one recording replayed, its row of the runs table) and the engines that
run the tasks: local worker processes, or Ray.

The task (:func:`replay_recording`) parses ``replay SOURCE`` with the real parser (so every option of
``replay`` has its default), puts the batch's options over it and calls ``replay``'s own command
function: the outputs are exactly those of ``ar-anchor replay``. Errors become the row's one-line reason;
nothing escapes it but a dead process.

Local engine (:func:`run_local`): ``N`` worker processes started with the ``spawn`` context (no forked
copies of OpenCV's or rerun's threads), each replaying one recording at a time, fed by the driver over a
pipe. With more than one worker each sets OpenCV to one thread (``cv2.setNumThreads(1)``): the recordings
are the parallelism, and N workers each with OpenCV's N threads would oversubscribe the cores. A worker that
dies (a crash in a decoder) fails its recording's row only; a new worker takes the next one. Workers ignore
SIGINT between tasks and turn it into ``KeyboardInterrupt`` during one, so Ctrl-C closes the replays'
outputs as ``replay`` does; the driver then waits for their rows, and ends what is left.

Ray engine (:func:`run_ray`): the same task function as a Ray task (``num_cpus=1``, no retries), imported
only when asked for. Sources and the output folder must be on storage every node sees at the same path.
Joining a cluster (:func:`ray_session`) is bounded: its address is first probed with a plain TCP connect
(:data:`RAY_PROBE_TIMEOUT_S`), then ``ray.init`` is given :data:`RAY_CONNECT_TIMEOUT_S`; Ray's own lines
meanwhile go to the debug log. A cluster that cannot be joined is one line, exit 2.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import multiprocessing
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from ..errors import ArAnchorError, InputError, printable
from ..targets import TargetId
from .recordings import STAMP_FILE, Recording
from .runs_table import empty_row

log = logging.getLogger(__name__)

KEEP_THREADS = "AR_ANCHOR_BATCH_KEEP_OPENCV_THREADS"  # "1": workers keep OpenCV's threads (bench batch measures it)
GRACE_S = 30.0  # after Ctrl-C: how long the replays get to close their outputs
RAY_PROBE_TIMEOUT_S = 5.0  # --ray ADDRESS: how long a TCP connect to the address may take
RAY_CONNECT_TIMEOUT_S = 60.0  # --ray ADDRESS: how long ray.init may take to join the cluster once it answers
_STATES = ("tracked", "ambiguous", "predicted", "interpolated")


@dataclass(frozen=True)
class BatchTask:
    """One recording to replay: where to, with which options (``replay``'s option names), the fingerprint
    stored beside its outputs when it succeeds, whether to score pair flips, the verbosity."""

    recording: Recording
    out_dir: Path
    options: dict[str, Any]
    fingerprint: str
    rigid_sheet: bool = False
    verbose: int = 0


def _log_to_stderr(name: str, verbose: int) -> None:
    """The ``ar_anchor`` loggers of this process to stderr, each line naming the recording."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    from .terminal import escaped_message

    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(f"ar-anchor: {printable(name)}: %(levelname)s: %(message)s"))
    handler.addFilter(escaped_message)  # (a file name's newline or ANSI escape is shown, not obeyed)
    root = logging.getLogger("ar_anchor")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _error_line(captured: str, code: int) -> str:
    """The reason replay printed (its last ``ar-anchor: error:`` line), else the exit code."""
    for line in reversed(captured.strip().splitlines()):
        if line.startswith("ar-anchor: error: "):
            return line.removeprefix("ar-anchor: error: ")
    return f"replay ended with exit code {code}"


def _fraction(count: float, total: float) -> float | None:
    return count / total if total else None


def _finite(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _is_learned_group(name: str) -> bool:
    """Is the target ``name`` (a key of ``summary.json``'s ``targets``) a learned group's board?"""
    from ..track.groups import is_learned_group

    try:
        return is_learned_group(TargetId.parse(name))
    except ValueError:
        return False


def fill_row(row: dict[str, Any], out_dir: Path, *, rigid_sheet: bool) -> None:
    """The row's figures from the run's ``summary.json`` (and ``poses.csv`` for the pair flips)."""
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return
    frames = int(summary.get("frames") or 0)
    row["frames"] = frames
    row["frames_with_markers"] = int(summary.get("frames_with_markers") or 0)
    row["fps"] = _finite(summary.get("fps"))
    row["detection_rate"] = _fraction(summary.get("frames_with_pose") or 0, frames)
    targets = summary.get("targets") or {}
    counts: dict[str, dict[str, int]] = {}
    for name, entry in targets.items():
        if _is_learned_group(name):
            continue  # a learned group (--learn-groups) lives for part of the run by design: not "lost" before it
        states = {state: int(n) for state, n in (entry.get("states") or {}).items()}
        states["lost"] = max(0, frames - sum(states.values()))
        counts[name] = states
    total = frames * len(counts)
    for state in ("tracked", "ambiguous", "lost"):
        row[f"{state}_fraction"] = _fraction(sum(c.get(state, 0) for c in counts.values()), total)
    row["targets"] = json.dumps(counts, sort_keys=True)
    if summary.get("ground_truth"):
        p95 = [_finite((e.get("rotation_error_deg") or {}).get("p95")) for e in targets.values()]
        row["rotation_error_p95_deg"] = max((v for v in p95 if v is not None), default=None)
        scored = sum(int(e.get("frames_scored") or 0) for e in targets.values())
        wrong = sum(int(e.get("wrong_frames") or 0) for e in targets.values())
        counted = any("wrong_frames" in e for e in targets.values())
        row["wrong_frame_rate"] = _fraction(wrong, scored) if counted else None
    if rigid_sheet and (out_dir / "poses.csv").is_file():
        from ..bench.real.scoring import read_poses_csv, score_rigid_sheet

        scores = score_rigid_sheet(read_poses_csv(out_dir / "poses.csv"))
        row["pair_frames"] = int(scores["pair_frames"])
        row["pair_flip_pct"] = _finite(scores["flip_pct"])
        row["relative_rotation_rms_deg"] = _finite(scores["rel_rot_rms_deg"])


def replay_recording(task: BatchTask, *, single_thread: bool = False) -> dict[str, Any]:
    """Replay one recording as ``ar-anchor replay`` would, into ``task.out_dir``; its row of the runs table.

    ``single_thread``: OpenCV on one thread (several recordings share the cores)."""
    import cv2

    from . import replay
    from .options import base_parser

    if single_thread and os.environ.get(KEEP_THREADS) != "1":
        cv2.setNumThreads(1)
    _log_to_stderr(task.recording.name, task.verbose)
    row = empty_row(task.recording, task.out_dir)
    started = time.monotonic()
    (task.out_dir / STAMP_FILE).unlink(missing_ok=True)  # (it would vouch for outputs this run replaces)
    captured = io.StringIO()
    try:
        parser, commands = base_parser()  # (the ar-anchor parser with replay alone: its options, their defaults)
        replay.add_parser(commands)
        args = parser.parse_args(["-q", "replay", task.recording.source])
        vars(args).update(task.options)
        args.out, args.quiet = task.out_dir, True
        args.batch_warned = True  # (what every recording shares, e.g. an assumed camera, the batch said once)
        with contextlib.redirect_stderr(captured), contextlib.redirect_stdout(io.StringIO()):
            code = int(args.func(args))
        row["status"], row["error"] = ("ok", None) if code == 0 else ("failed", _error_line(captured.getvalue(), code))
    except ArAnchorError as err:
        row["status"], row["error"] = "failed", printable(err)
    except KeyboardInterrupt:
        row["status"], row["error"] = "interrupted", "interrupted (outputs written so far are complete)"
    except Exception as err:  # noqa: BLE001 - a bug in one recording's run fails its row, not the batch
        log.debug("internal error", exc_info=True)
        row["status"], row["error"] = "failed", f"internal error: {type(err).__name__}: {printable(err)}"
    except SystemExit as err:  # (argparse: a SOURCE it refuses)
        row["status"], row["error"] = "failed", f"replay refused its arguments ({err.code})"
    fill_row(row, task.out_dir, rigid_sheet=task.rigid_sheet)
    row["wall_s"] = time.monotonic() - started
    if row["status"] == "ok":
        stamp = {"fingerprint": task.fingerprint, "row": row}
        (task.out_dir / STAMP_FILE).write_text(json.dumps(stamp, indent=2) + "\n")
    return row


def _failed(task: BatchTask, reason: str, status: str = "failed") -> dict[str, Any]:
    row = empty_row(task.recording, task.out_dir)
    row["status"], row["error"] = status, reason
    return row


# ============================================================================ local processes


def _worker(conn: Connection, single_thread: bool) -> None:
    """A local worker: replays the tasks the driver sends, one at a time, until it sends None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # between tasks: the driver decides
    try:
        while True:
            task = conn.recv()
            if task is None:
                return
            signal.signal(signal.SIGINT, signal.default_int_handler)
            try:
                row = replay_recording(task, single_thread=single_thread)
            finally:
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            conn.send(row)
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return


def _death(process: multiprocessing.process.BaseProcess) -> str:
    process.join(timeout=5.0)
    code = process.exitcode
    if code is not None and code < 0:
        try:
            return f"the worker process died (signal {signal.Signals(-code).name})"
        except ValueError:
            return f"the worker process died (signal {-code})"
    return f"the worker process died (exit code {code})"


def run_local(tasks: list[BatchTask], jobs: int, done: Callable[[dict[str, Any]], None]) -> None:
    """Run ``tasks`` on ``jobs`` local worker processes (see the module doc), handing each row to ``done``
    as it comes. Ctrl-C: the running replays are interrupted, their rows handed over, then it re-raises."""
    context = multiprocessing.get_context("spawn")
    count = max(1, min(jobs, len(tasks)))
    single_thread = count > 1
    pending = deque(tasks)
    busy: dict[Connection, tuple[Any, BatchTask]] = {}  # a worker's pipe -> (its process, its task)

    def start_worker() -> None:
        parent, child = context.Pipe()
        process = context.Process(target=_worker, args=(child, single_thread), daemon=True, name="ar-anchor-batch")
        process.start()
        child.close()
        task = pending.popleft()
        parent.send(task)
        busy[parent] = (process, task)

    def collect(timeout: float | None) -> None:
        for conn in wait(list(busy), timeout=timeout):
            process, task = busy.pop(conn)  # type: ignore[call-overload]
            try:
                row = conn.recv()
            except (EOFError, OSError):  # the worker died: its recording fails, a new worker goes on
                conn.close()
                done(_failed(task, _death(process)))
                if pending:
                    start_worker()
                continue
            done(row)
            if pending:
                task = pending.popleft()
                conn.send(task)
                busy[conn] = (process, task)
            else:
                with contextlib.suppress(OSError):
                    conn.send(None)
                conn.close()
                process.join(timeout=5.0)

    try:
        for _ in range(count):
            start_worker()
        while busy:
            collect(None)
    except KeyboardInterrupt:
        pending.clear()
        _wind_down(busy, collect, done)
        raise
    finally:
        for process, _ in busy.values():
            if process.is_alive():
                process.kill()
            process.join(timeout=5.0)


def _wind_down(
    busy: dict[Connection, tuple[Any, BatchTask]],
    collect: Callable[[float | None], None],
    done: Callable[[dict[str, Any]], None],
) -> None:
    """After Ctrl-C: each running replay is interrupted (a terminal's Ctrl-C reached it already; SIGINT
    otherwise, after a moment) and given :data:`GRACE_S` to close its outputs; what is left is killed."""
    deadline = time.monotonic() + GRACE_S
    signalled = False
    with contextlib.suppress(KeyboardInterrupt):  # (a second Ctrl-C: stop waiting)
        collect(2.0)
        while busy and time.monotonic() < deadline:
            if not signalled:
                for process, _ in busy.values():
                    with contextlib.suppress(ProcessLookupError, TypeError):
                        os.kill(process.pid, signal.SIGINT)
                signalled = True
            collect(min(1.0, max(0.0, deadline - time.monotonic())))
    for conn, (process, task) in list(busy.items()):
        process.kill()
        process.join(timeout=5.0)
        conn.close()
        del busy[conn]
        done(_failed(task, "interrupted: the replay did not close in time (its outputs may be incomplete)",
                     "interrupted"))  # fmt: skip


# ============================================================================ Ray


def require_ray() -> Any:
    """The ``ray`` module; :class:`InputError` (exit 2) when it is not installed."""
    try:
        import ray
    except ImportError:
        raise InputError("--ray: Ray is not installed (pip install 'ar-anchor[cluster]')") from None
    return ray


def _ray_endpoint(ray: Any, address: str) -> tuple[str, int] | None:
    """The (host, port) that joining ``address`` connects to first; None when it cannot be told (Ray's way of
    finding ``auto``'s cluster moved). :class:`InputError` when ``auto`` finds no cluster at all."""
    if address == "auto":
        try:
            from ray._private.services import canonicalize_bootstrap_address

            address = canonicalize_bootstrap_address("auto") or ""
        except ConnectionError:
            raise InputError(
                "--ray auto: no running Ray cluster found on this machine (RAY_ADDRESS unset, no `ray start` "
                "cluster): start one with `ray start --head`, or give its address, or --ray alone for a local Ray"
            ) from None
        except Exception:  # noqa: BLE001 - Ray's internals changed: joining is still bounded below
            return None
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def _probe(address: str, host: str, port: int) -> None:
    """A plain TCP connect to ``host:port``; :class:`InputError` naming ``--ray`` when it fails."""
    try:
        with socket.create_connection((host, port), timeout=RAY_PROBE_TIMEOUT_S):
            return
    except ConnectionRefusedError:
        why = "connection refused: nothing listens there"
    except TimeoutError:
        why = f"no answer within {RAY_PROBE_TIMEOUT_S:g} s"
    except socket.gaierror as err:
        why = f"unknown host ({err.strerror or err})"
    except OSError as err:
        why = err.strerror or str(err)
    raise InputError(
        f"--ray {printable(address)}: cannot reach {printable(host)}:{port} ({why}); is a Ray cluster running there "
        "(`ray start --head`)?"
    )


@contextlib.contextmanager
def _stderr_to_log() -> Iterator[None]:
    """What is written to file descriptor 2 (Ray's own C++ and Python lines) while the block runs goes to the
    debug log instead."""
    with tempfile.TemporaryFile() as held:
        try:
            saved = os.dup(2)
        except OSError:
            yield
            return
        sys.stderr.flush()
        try:
            os.dup2(held.fileno(), 2)
            try:
                yield
            finally:
                sys.stderr.flush()
                os.dup2(saved, 2)
        finally:
            os.close(saved)
        held.seek(0)
        for line in held.read(1 << 16).decode("utf-8", "replace").splitlines():
            if line.strip():
                log.debug("ray: %s", line.strip())


def _abandon(ray: Any) -> None:
    """A ``ray.init`` that never returned is left to its thread: Ray's exit handler, which would wait for it,
    is taken off (the process ends at once)."""
    import atexit

    for module in ("ray._private.worker", "ray"):
        with contextlib.suppress(Exception):
            atexit.unregister(sys.modules[module].shutdown)


def _join(ray: Any, address: str) -> threading.Event:
    """``ray.init(address)`` within :data:`RAY_CONNECT_TIMEOUT_S` (on a thread: Ctrl-C is not held up), Ray's
    lines to the debug log; :class:`InputError` naming ``--ray`` when it fails or takes longer.

    The thread lives on until the returned event is set (after ``ray.shutdown``): a process Ray starts is
    bound to the thread that started it (its parent-death signal) and would end with it."""
    outcome: dict[str, BaseException] = {}
    joined, release = threading.Event(), threading.Event()

    def init() -> None:
        try:
            ray.init(address=address, include_dashboard=False, logging_level=logging.WARNING)
        except BaseException as err:  # noqa: BLE001 - handed to the main thread
            outcome["error"] = err
            return
        joined.set()
        release.wait()

    thread = threading.Thread(target=init, name="ray-connect", daemon=True)
    deadline = time.monotonic() + RAY_CONNECT_TIMEOUT_S
    try:
        with _stderr_to_log():
            thread.start()
            while thread.is_alive() and not joined.is_set() and time.monotonic() < deadline:
                thread.join(0.1)
    except BaseException:
        _abandon(ray)
        raise
    if thread.is_alive() and not joined.is_set():
        _abandon(ray)
        raise InputError(
            f"--ray {printable(address)}: the address answers but no Ray cluster was joined within "
            f"{RAY_CONNECT_TIMEOUT_S:g} s (is it a Ray head's address, of the same Ray version?)"
        )
    if "error" in outcome:
        err = outcome["error"]
        first = (str(err).strip().splitlines() or [""])[0]
        raise InputError(f"--ray {printable(address)}: cannot join the Ray cluster ({type(err).__name__}: "
                         f"{printable(first)})")  # fmt: skip
    return release


def _start_local(ray: Any, cpus: int | None) -> None:
    """A local Ray of ``cpus`` CPUs (default: the usable cores), Ray's lines meanwhile to the debug log.
    ``RAY_ADDRESS`` would make ``ray.init`` join that cluster instead (and refuse ``num_cpus``): it is set aside
    meanwhile, with a warning."""
    joined = os.environ.pop("RAY_ADDRESS", None)
    if joined:
        log.warning("--ray: RAY_ADDRESS=%s ignored: --ray alone starts a local Ray (--ray auto joins it)", joined)
    try:
        with _stderr_to_log():  # (Ray's own lines while it starts: to the debug log)
            ray.init(num_cpus=cpus or usable_cores(), include_dashboard=False, logging_level=logging.WARNING)
    finally:
        if joined is not None:
            os.environ["RAY_ADDRESS"] = joined


@contextlib.contextmanager
def ray_session(address: str, cpus: int | None) -> Iterator[Any]:
    """Ray for a batch, shut down when the block ends (unless it was running before): the cluster at
    ``address`` (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``) joined within bounded time (see the module doc),
    or a local Ray of ``cpus`` CPUs (``address`` empty). :class:`InputError` (exit 2) when Ray is not installed
    or the cluster cannot be reached."""
    ray = require_ray()
    if ray.is_initialized():  # (a caller's own Ray)
        yield ray
        return
    release = None
    if address:
        endpoint = _ray_endpoint(ray, address)
        if endpoint is not None:
            _probe(address, *endpoint)
        release = _join(ray, address)
    else:
        _start_local(ray, cpus)
    try:
        yield ray
    finally:
        try:
            ray.shutdown()
        finally:
            if release is not None:
                release.set()


def _ray_task(task: BatchTask) -> dict[str, Any]:
    """The Ray task: one recording, OpenCV on one thread (each task holds one CPU)."""
    return replay_recording(task, single_thread=True)


def run_ray(tasks: list[BatchTask], address: str, cpus: int | None, done: Callable[[dict[str, Any]], None]) -> None:
    """Run ``tasks`` as Ray tasks: on the cluster at ``address`` (``auto``, ``ray://host:10001``), or on a
    local Ray started here (``address`` empty; ``cpus`` CPUs, default all) and shut down at the end (see
    :func:`ray_session`; a Ray already running in this process is used as it is)."""
    with ray_session(address, cpus) as ray:
        remote = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
        refs = {remote.remote(task): task for task in tasks}
        try:
            _ray_collect(ray, refs, done, timeout=None)
        except KeyboardInterrupt:
            for ref in refs:
                with contextlib.suppress(Exception):
                    ray.cancel(ref)  # a KeyboardInterrupt in the task: the replay closes its outputs
            with contextlib.suppress(KeyboardInterrupt):
                _ray_collect(ray, refs, done, timeout=GRACE_S)
            for task in refs.values():
                done(_failed(task, "interrupted before it finished", "interrupted"))
            raise


def _ray_collect(
    ray: Any, refs: dict[Any, BatchTask], done: Callable[[dict[str, Any]], None], timeout: float | None
) -> None:
    """Hand each finished task's row to ``done`` until none is left (or ``timeout`` s have passed)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while refs:
        left = None if deadline is None else max(0.0, deadline - time.monotonic())
        if left == 0.0:
            return
        ready, _ = ray.wait(list(refs), num_returns=1, timeout=left)
        for ref in ready:
            task = refs.pop(ref)
            try:
                row = ray.get(ref)
            except Exception as err:  # noqa: BLE001 - the task's process died, or it was cancelled
                first = (str(err).strip().splitlines() or [""])[0]
                cancelled = type(err).__name__ == "TaskCancelledError"
                row = _failed(task, "interrupted" if cancelled else f"ray: {type(err).__name__}: {printable(first)}",
                              "interrupted" if cancelled else "failed")  # fmt: skip
            done(row)


def usable_cores() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)
