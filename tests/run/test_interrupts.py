"""InterruptGuard in a process of its own: the run's second signal ends it at once, wherever the first one
was held; a single signal never cuts the closing short."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

from ar_anchor.errors import EXIT_INTERRUPTED

_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, threading, time
    from ar_anchor.run.interrupts import InterruptGuard

    SIGNALS, WRITE_S, CLOSE_S, STUCK = {signals!r}, {write_s!r}, {close_s!r}, {stuck!r}

    def send():
        for at in SIGNALS:
            time.sleep(at)
            os.kill(os.getpid(), signal.SIGINT)

    def abandon():
        print("abandoned", flush=True)
        return ["recording.rrd"]

    threading.Thread(target=send, daemon=True).start()
    try:
        with InterruptGuard(abandon) as guard:
            try:
                with guard.critical():  # one frame's write, waiting (as on an output thread that cannot keep up)
                    end = time.monotonic() + WRITE_S
                    while time.monotonic() < end or STUCK:  # STUCK: a write that never returns
                        time.sleep(0.05)
            finally:
                guard.hold()
                time.sleep(CLOSE_S)  # a flush held by a viewer that stopped reading
                print("closed", flush=True)
    except KeyboardInterrupt:
        sys.exit(130)
    """
)


def _run(signals: list[float], *, write_s: float, close_s: float, stuck: bool = False):
    script = _SCRIPT.format(signals=signals, write_s=write_s, close_s=close_s, stuck=stuck)
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    return result, time.monotonic() - started


@pytest.mark.slow
def test_two_signals_held_while_a_frame_is_written_end_the_run_once_it_closes():
    # given two Ctrl-C while one frame's outputs are written (both held: the handler sees them while the
    # frame is critical), then a closing that would take 20 s
    result, took = _run([0.3, 0.3], write_s=1.5, close_s=20.0)
    # then the process ends as the closing begins, abandoned, with exit 130 and one line
    assert result.returncode == EXIT_INTERRUPTED, result
    assert "abandoned" in result.stdout and "closed" not in result.stdout, result
    assert result.stderr.startswith("ar-anchor: interrupted again"), result
    assert took < 10.0, took


@pytest.mark.slow
def test_two_signals_to_a_main_thread_stuck_in_a_frame_end_the_run():
    result, took = _run([0.3, 0.3], write_s=0.0, close_s=0.0, stuck=True)
    assert result.returncode == EXIT_INTERRUPTED, result
    assert "abandoned" in result.stdout, result
    assert took < 15.0, took


@pytest.mark.slow
def test_one_signal_lets_the_closing_finish():
    # given one Ctrl-C while a frame is written, and a closing of 1.5 s
    result, took = _run([0.3], write_s=0.6, close_s=1.5)
    # then the closing finishes, nothing is abandoned, and the run ends interrupted
    assert result.returncode == EXIT_INTERRUPTED, result
    assert "closed" in result.stdout and "abandoned" not in result.stdout, result
    assert result.stderr == "", result
    assert took >= 1.5


@pytest.mark.slow
def test_a_second_signal_during_the_closing_cuts_it_short():
    result, took = _run([0.3, 1.5], write_s=0.5, close_s=20.0)
    assert result.returncode == EXIT_INTERRUPTED, result
    assert "abandoned" in result.stdout and "closed" not in result.stdout, result
    assert took < 10.0, took
