"""The live synthetic run ``bench run`` and ``bench speed`` both time: ``ar-anchor live --device synthetic``
at 1080p started as a user starts it, its resident set size sampled, stopped with SIGINT."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from ...errors import ArAnchorError
from .processes import cli

__all__ = ["LIVE_FPS", "LIVE_SIZE", "SAMPLE_S", "live_run", "rss_mb", "stages"]

LIVE_SIZE = (1920, 1080)
LIVE_FPS = 30.0
SAMPLE_S = 5.0


def rss_mb(pid: int) -> float | None:
    """The resident set size (MB) of process ``pid``, from ``/proc/<pid>/status``; None when unreadable."""
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def stages(summary: dict[str, Any]) -> dict[str, Any]:
    """A run's ``summary.json`` latency figures by stage name (without the ``_ms`` suffix)."""
    return {stage.removesuffix("_ms"): values for stage, values in summary.get("latency_ms", {}).items()}


def _sigint_as_a_user_has_it() -> None:
    """In the live run's process before it starts: SIGINT back to its default. A bench started in the
    background (``cmd &`` in a script, ``nohup``) has it ignored, the child would inherit that, and a live run
    keeps ignoring a signal its parent ignored (as it should: that is how a background job is started)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def live_run(
    tmp: Path, seconds: float, name: str, config: str | None = None, extra: tuple[str, ...] = ()
) -> dict[str, Any]:
    """A live synthetic 1080p run for ``seconds`` after the camera opened, then SIGINT. ``config``: a
    tracker TOML (the synthetic scene holds the markers and boards it names); ``extra``: more options
    (``--no-recording``)."""
    out = tmp / name
    width, height = LIVE_SIZE
    command = cli(
        "live", "--device", "synthetic", "--width", str(width), "--height", str(height), "--fps", str(LIVE_FPS)
    )
    command += [*extra, "--out", str(out)]
    if config is not None:
        path = tmp / f"{name}.toml"
        path.write_text(config)
        command += ["--config", str(path)]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_sigint_as_a_user_has_it
    )
    samples: list[tuple[float, float]] = []
    started: float | None = None
    try:
        while process.poll() is None:
            now = time.monotonic()
            if started is None and (out / "poses.csv").exists():
                started = now  # the camera's clip is rendered and frames flow
            if started is not None:
                rss = rss_mb(process.pid)
                if rss is not None:
                    samples.append((now - started, rss))
                if now - started >= seconds:
                    process.send_signal(signal.SIGINT)
                    break
            time.sleep(SAMPLE_S if started is not None else 0.5)
        try:
            _, stderr = process.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            raise ArAnchorError(f"bench: the live run ({out}) did not end within 120 s of its SIGINT") from None
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    summary = json.loads((out / "summary.json").read_text())
    return {
        "exit_code": process.returncode,
        "status": summary["status"],
        "seconds": seconds,
        "frames": summary["frames"],
        "fps": summary["fps"],
        "live": summary.get("live", {}),
        "frames_not_logged": summary.get("frames_not_logged", 0),
        "stages": stages(summary),
        "rss_mb": samples,
        "stderr_tail": stderr.strip().splitlines()[-3:],
    }
