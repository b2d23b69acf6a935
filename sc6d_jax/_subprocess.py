"""Run ``sc6d`` sub-commands as child processes with their output in a log file.

Used by the experiment scripts (``experiments/sweep.py``, ``experiments/lmo.py``), which run
every stage as a separate process so that an interrupted experiment can resume.
"""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence


class StageFailed(RuntimeError):
    """A ``sc6d`` sub-command exited with a non-zero status."""


def run_sc6d(args: Sequence[Any], log: Path, heartbeat: Callable[[], None] | None = None,
             every_s: float = 30.0) -> float:
    """``python -m sc6d_jax.cli ARGS`` with its output in ``log``; the seconds it took.

    ``heartbeat`` is called every ``every_s`` seconds while the command runs (progress lines).
    Raises StageFailed with the log's tail on a non-zero exit; the child is terminated when this
    process is interrupted.
    """
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "sc6d_jax.cli", *map(str, args)]
    t0 = time.perf_counter()
    with open(log, "w", encoding="utf-8") as f:
        f.write("$ sc6d " + shlex.join(cmd[3:]) + "\n")
        f.flush()
        child = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        try:
            while True:
                try:
                    rc = child.wait(timeout=every_s)
                    break
                except subprocess.TimeoutExpired:
                    if heartbeat is not None:
                        heartbeat()
        except BaseException:
            child.terminate()
            try:
                child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.kill()
            raise
    if rc != 0:
        tail = "\n".join(log.read_text(encoding="utf-8", errors="replace").splitlines()[-15:])
        raise StageFailed(f"`sc6d {args[0]}` exited with status {rc} (log {log}):\n{tail}")
    return time.perf_counter() - t0


def _on_term(signum: int, frame: Any) -> None:  # pragma: no cover - a kill of the experiment
    raise KeyboardInterrupt(f"signal {signum}")


def experiment_main(prog: str, body: Callable[[], int]) -> int:
    """Run an experiment's ``body`` as a command: SIGTERM interrupts it like Ctrl-C (so the
    running ``sc6d`` child is terminated too), bad input and failed stages end with one error
    line and status 2, an interruption with status 130 and a hint to rerun (experiments resume).
    The previous SIGTERM handler is restored afterwards."""
    previous = signal.signal(signal.SIGTERM, _on_term)
    try:
        return body()
    except (ValueError, FileNotFoundError, StageFailed) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
