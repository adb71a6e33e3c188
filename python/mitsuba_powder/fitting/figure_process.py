"""A second Python process that draws a fit's figures, started before the fit.

The ``fit`` command's figures cost about a third of a second of matplotlib import and half a
second of drawing, after an optimiser of a few seconds. Started before the fit, the process
imports matplotlib while the optimiser runs, then draws the figures while the fitting process
writes ``fit.json``: the figures then add little to the command's time (measured in
docs/fitting.md, "Speed"). The jobs travel as a pickle on the process's standard input (numbers
and file paths only: the plugin is not needed to draw). A process that cannot be started is no
error: :func:`mitsuba_powder.fitting.report.write_report` then draws in its own process.

Run as ``python -m mitsuba_powder.fitting.figure_process``; it reads one pickled job list
(:func:`mitsuba_powder.fitting.figures.draw`) and exits with 0 once every figure is written.
"""

from __future__ import annotations

import pickle
import subprocess
import sys

__all__ = ["FigureProcess"]


class FigureProcess:
    """The drawing process; use as a context manager (it is ended on leaving, if still
    running). One process: a second one, on the 2-core machine, slowed the fit more than it
    sped up the drawing (docs/fitting.md, "Speed")."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        except OSError:
            self._proc = None

    @property
    def running(self) -> bool:
        """Whether the process started and has not been given its jobs yet."""
        return (self._proc is not None and self._proc.stdin is not None
                and not self._proc.stdin.closed and self._proc.poll() is None)

    def submit(self, jobs: list[tuple[str, dict]]) -> bool:
        """Send ``jobs`` to the process; False when it is not running (draw them yourself)."""
        if not self.running:
            return False
        try:
            self._proc.stdin.write(pickle.dumps(jobs, protocol=pickle.HIGHEST_PROTOCOL))
            self._proc.stdin.close()
        except (BrokenPipeError, OSError):
            return False
        return True

    def wait(self) -> None:
        """Wait until every figure is written.

        Raises:
            RuntimeError: the process failed; its error output is in the message.
        """
        if self._proc is None:
            return
        err = self._proc.stderr.read()
        self._proc.stderr.close()
        if self._proc.wait() != 0:
            text = err.decode(errors="replace").strip()[-3000:]
            raise RuntimeError(f"drawing the fit's figures failed (exit "
                               f"{self._proc.returncode}): {text}")

    def close(self) -> None:
        """End the process if it still runs (an error before its jobs were sent)."""
        if self._proc is None:
            return
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        for pipe in (self._proc.stdin, self._proc.stderr):
            if pipe is not None and not pipe.closed:
                pipe.close()

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def main() -> int:
    """The process: import matplotlib, read the jobs, draw them."""
    from .figures import draw, preload

    preload()
    data = sys.stdin.buffer.read()
    if not data:  # the fit failed or drew in its own process: nothing to do
        return 0
    draw(pickle.loads(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
