"""What a person watching a training run sees: a progress bar on a terminal, else (a SLURM or
nohup log) a line every :data:`PROGRESS_EVERY_S` seconds, and a line per evaluation; the long
phases between two agent steps (the burst of updates, an evaluation, a checkpoint, the loading
of one) show their own (:func:`phase`); in a batch of runs (``--seeds``, ``--runs``) each run's
lines say which seed they are of (:func:`member_lines`).  ``train.progress=false`` shows none of
it: neither bars nor progress lines."""
from __future__ import annotations

import contextlib
import contextvars
import sys
import threading
import time
from typing import Callable, Iterator, Optional

from tqdm import tqdm

PROGRESS_EVERY_S = 60.0
"""Seconds of wall time between progress lines when stdout is not a terminal (a SLURM or nohup
log): agent step, frames per second, ETA and the last episode's return; inside a long phase
(:func:`phase`), what the phase has done so far."""

BAR_REFRESH_S = 1.0
"""Seconds between redraws of a phase's bar, so that its elapsed time runs while nothing advances."""

PHASE_LINE_MIN_S = 0.01
"""The fewest seconds between two lines of a phase: ``every_s`` of 0 (a progress line every
agent step, as tests ask) would otherwise print lines without a pause while the phase lasts."""


class Eta:
    """The time left until agent step ``total``, from the rate of the phase that remains.

    The seed phase (random actions, no updates) runs many times faster than the updates after
    it, so its rate says nothing about the rest of a run: until updates run there is no
    estimate, and :meth:`text` says after which agent step there will be one.  The rate is
    measured from the first agent step done after ``learning_starts``, which also leaves out
    the one-off burst of updates there; evaluations and checkpoints count into it, as they
    recur.  ``clock`` gives seconds (``time.monotonic``; a test injects its own values).
    """

    def __init__(self, total: int, learning_starts: int, clock: Callable[[], float] = time.monotonic):
        self.total, self.learning_starts, self.clock = total, learning_starts, clock
        self.since: Optional[tuple[float, int]] = None
        """``(time, agent step)`` the rate is measured from; None until an agent step past
        ``learning_starts`` is done."""

    def update(self, step: int) -> None:
        """Agent step ``step`` is done."""
        if self.since is None and step > self.learning_starts:
            self.since = (self.clock(), step)

    def seconds(self, step: int) -> Optional[float]:
        """Seconds left at agent step ``step``; None while there is no rate of updates yet."""
        if self.since is None or step <= self.since[1]:
            return None
        started, first = self.since
        return max(self.total - step, 0) * (self.clock() - started) / (step - first)

    def text(self, step: int) -> str:
        """``3:12:40``, or ``after agent step 1,002`` while there is no estimate yet."""
        left = 0 if step >= self.total else self.seconds(step)
        if left is not None:
            return _hms(left)
        first = self.since[1] if self.since is not None else self.learning_starts + 1
        return f"after agent step {first + 1:,}"


class _Bar(tqdm):
    """tqdm with the :class:`Eta` estimate (:attr:`eta`) in place of its own, which comes from
    the recent rate, the seed phase's while it lasts."""

    FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, ETA {eta}, {rate_fmt}{postfix}]"
    eta = ""

    @property
    def format_dict(self):
        return dict(super().format_dict, eta=self.eta)


class Progress:
    """The progress of one training process from agent step ``step`` / frame ``frame`` to
    ``total`` agent steps.

    Args:
        total: the budget in agent steps.
        step, frame: where this process starts (a resume starts past 0).
        desc: the bar's label.
        bar: show progress (``train.progress``): a bar, or lines (:func:`display`); False: neither.
        every_s: seconds between progress lines (a log, :func:`display`).
        learning_starts: the agent step from which the agent updates (:class:`Eta`).
    """

    @classmethod
    def of_run(cls, cfg, state, every_s: float = PROGRESS_EVERY_S) -> "Progress":
        """The progress of a training of ``cfg`` from where its :class:`~imssr.training.state.RunState`
        ``state`` stands."""
        return cls(cfg.total_steps, state.step, state.frame, f"{cfg.algo} {cfg.env.task} s{cfg.train.seed}",
                   bar=cfg.train.progress, every_s=every_s, learning_starts=state.learning_starts)

    def __init__(self, total: int, step: int, frame: int, desc: str, bar: bool = True,
                 every_s: float = PROGRESS_EVERY_S, learning_starts: int = 0):
        self.total, self.every_s = total, every_s
        self.eta = Eta(total, learning_starts)
        shown = display(bar)
        self.bar = _Bar(total=total, initial=min(step, total), unit="step", disable=shown != "bar",
                        dynamic_ncols=True, desc=desc, bar_format=_Bar.FORMAT)
        self.bar.eta = self.eta.text(step)
        self.lines = shown == "lines"
        self.started, self.start_frame = time.monotonic(), frame
        self.next_line = self.started + every_s

    def step(self, step: int, frame: int, last_return: Optional[float]) -> None:
        """One agent step done, now at ``step`` / ``frame``: the bar moves, or a line is due."""
        self.eta.update(step)
        if not self.bar.disable:
            self.bar.eta = self.eta.text(step)
        self.bar.update(1)
        if self.lines and time.monotonic() >= self.next_line:
            now = time.monotonic()
            self.next_line = now + self.every_s
            print(progress_line(step, self.total, frame - self.start_frame, now - self.started,
                                self.eta.text(step), last_return), flush=True)

    def episode_end(self, episode_return: float, fps: float, frame: int) -> None:
        """The bar shows the episode just finished."""
        self.bar.set_postfix(ret=f"{episode_return:.1f}", fps=f"{fps:.0f}", frame=frame)

    def say(self, text: str) -> None:
        """A line of its own, above the bar when it shows."""
        if not self.bar.disable:
            self.bar.write(text)
        else:
            print(text, flush=True)

    def close(self) -> None:
        self.bar.close()


def display(show: bool) -> Optional[str]:
    """How progress shows in this process: ``"bar"`` when stderr is a terminal, ``"lines"`` when
    neither stderr nor stdout is (a SLURM or nohup log, a notebook), else (stdout alone on a
    terminal, ``2>log``) None; None too when ``show`` (``train.progress``) is off."""
    if not show:
        return None
    if _isatty(sys.stderr):
        return "bar"
    return None if _isatty(sys.stdout) else "lines"


class Phase:
    """A long phase between two agent steps as :func:`phase` shows it: ``done`` of ``total``
    ``unit`` (None: a phase that counts nothing, a checkpoint's write)."""

    def __init__(self, what: str, total: Optional[int], unit: str, done: int, bar: Optional[tqdm]):
        self.what, self.total, self.unit, self.done, self.bar = what, total, unit, done, bar

    def advance(self, n: int = 1) -> None:
        """``n`` more ``unit`` done."""
        self.done += n
        if self.bar is not None:
            self.bar.update(n)

    def line(self, seconds: float) -> str:
        """``imssr: agent step 1,000: burst of updates, 230/1,000 updates done, 0:04:12 so far``."""
        count = "" if self.total is None else f", {self.done:,}/{self.total:,} {self.unit} done"
        return f"imssr: {self.what}{count}, {_hms(seconds)} so far"


_current: contextvars.ContextVar[Optional[Phase]] = contextvars.ContextVar("imssr_phase", default=None)


def advance(n: int = 1) -> None:
    """``n`` more units of the innermost open :func:`phase` done (none open: nothing): for code
    deep below the phase's opener, such as each episode of an evaluation."""
    current = _current.get()
    if current is not None:
        current.advance(n)


@contextlib.contextmanager
def phase(what: str, total: Optional[int] = None, unit: str = "", done: int = 0, show: bool = True,
          every_s: Optional[float] = None) -> Iterator[Phase]:
    """Show the progress of a long phase between two agent steps (the run's own progress moves
    only from one agent step to the next): the block gets a :class:`Phase` at ``done`` of
    ``total`` ``unit``, which :meth:`Phase.advance` (or :func:`advance`, from code below) counts up.

    How it shows is :func:`display`'s: on a terminal, a bar of its own below the run's, removed
    when the block ends; in a log, a line (:meth:`Phase.line`) every ``every_s`` seconds (None:
    :data:`PROGRESS_EVERY_S` as it is then) while the block lasts, so none for a shorter block;
    with ``show`` off, nothing.  A daemon thread redraws the bar (its elapsed time runs while
    nothing advances, as in a checkpoint's write) or writes the lines.  It reads the count and the
    clock only, never torch or a random generator, so the training's numbers are those of a run
    without it; and it has stopped when the block is left, by an exception too, so nothing is
    printed after it."""
    shown = display(show)
    every_s = PROGRESS_EVERY_S if every_s is None else every_s
    bar = None if shown != "bar" else tqdm(
        total=total, initial=done, desc=what, unit=f" {unit}" if unit else "it", leave=False, dynamic_ncols=True,
        bar_format=None if total is not None else "{desc}: {elapsed}")
    current, stop = Phase(what, total, unit, done, bar), threading.Event()
    thread = None if shown is None else threading.Thread(
        target=_show_phase, args=(current, stop, every_s, sys.stdout), name="imssr-progress", daemon=True)
    token = _current.set(current)
    try:
        if thread is not None:
            thread.start()
        yield current
    finally:
        stop.set()
        if thread is not None and thread.is_alive():
            thread.join()
        if bar is not None:
            bar.close()
        _current.reset(token)


def _show_phase(current: Phase, stop: threading.Event, every_s: float, stream) -> None:
    """The thread of :func:`phase`: until ``stop``, redraw ``current``'s bar, or write its line
    every ``every_s`` seconds to ``stream`` (the stdout the phase began on), the line and its
    newline in one write, flushed (a batch's run's stdout, :func:`member_lines`: with the run's
    label, at once even where the run's other lines are held)."""
    label = stream.label if isinstance(stream, _MemberStdout) else None
    stream = stream.stream if label is not None else stream
    started = time.monotonic()
    while not stop.wait(BAR_REFRESH_S if current.bar is not None else max(every_s, PHASE_LINE_MIN_S)):
        try:
            if current.bar is not None:
                current.bar.refresh()
            else:
                line = current.line(time.monotonic() - started)
                stream.write((line if label is None else with_member(label, line)) + "\n")
                stream.flush()
        except (OSError, ValueError):  # a stream closed under the thread: the training goes on
            return


def progress_line(step: int, total: int, frames: int, seconds: float, eta: str, last_return: Optional[float]) -> str:
    """``imssr: agent step 1,200/500,000 (0.2%), 310 frames/s, ETA 3:12:40, last episode return 12.5``:
    the frame rate over this process's training so far (``frames`` in ``seconds``), the
    estimate ``eta`` (:meth:`Eta.text`)."""
    seconds = max(seconds, 1e-9)
    ret = "none yet" if last_return is None else f"{last_return:.1f}"
    return (f"imssr: agent step {step:,}/{total:,} ({100 * step / max(total, 1):.1f}%), "
            f"{frames / seconds:,.0f} frames/s, ETA {eta}, last episode return {ret}")


def eval_summary(rows: list[dict]) -> str:
    """``12.5 ± 3.0`` for one scene's ``eval.csv`` row, ``train 12.5 ± 3.0, color_hard ...`` for several."""
    text = ", ".join(f"{r['mode']} {r['return_mean']:.1f} ± {r['return_std']:.1f}" for r in rows)
    return text if len(rows) > 1 else text.split(" ", 1)[1]


def member_labels(seeds: list[int], algos: list[str], paths: list[str]) -> list[str]:
    """What each run of a batch is called in its console lines: ``seed 3`` when the seeds tell the
    runs apart, else ``im-curl seed 3`` (``--runs`` of CURL and IM-CURL), else its directory."""
    for labels in ([f"seed {s}" for s in seeds], [f"{a} seed {s}" for a, s in zip(algos, seeds)]):
        if len(set(labels)) == len(labels):
            return labels
    return list(paths)


def with_member(label: str, line: str) -> str:
    """``line`` of the run ``label`` of a batch: ``imssr: seed 3: warning: ...``, ``seed 3: eval step ...``."""
    if not line.strip():
        return line
    if line.startswith("imssr: "):
        return f"imssr: {label}: {line[len('imssr: '):]}"
    return f"{label}: {line}"


class _MemberStdout:
    """``sys.stdout`` for the lines of one run of a batch: each whole line is written to
    ``stream`` with the run's label (:func:`with_member`), or kept in ``held`` to be said later."""

    def __init__(self, stream, label: str, held: Optional[list[str]]):
        self.stream, self.label, self.held = stream, label, held
        self._partial = ""

    def write(self, text: str) -> int:
        self._partial += text
        *lines, self._partial = self._partial.split("\n")
        for line in lines:
            if self.held is not None:
                self.held.append(line)
            else:
                self.stream.write(with_member(self.label, line) + "\n")
        return len(text)

    def flush(self) -> None:
        if self.held is None:
            self.stream.flush()

    def end(self) -> None:
        """The block is over: a line left without its newline is written too."""
        if self._partial:
            self.write("\n")
        self.flush()

    def __getattr__(self, name: str):  # isatty, encoding, fileno: the stream's
        return getattr(self.stream, name)


@contextlib.contextmanager
def member_lines(label: str, held: Optional[list[str]] = None) -> Iterator[None]:
    """Inside the block, every line printed to stdout is of the run ``label`` of a batch
    (:func:`member_labels`): written with the label (:func:`with_member`), or, with ``held``,
    appended there (without it) for :func:`say_held`.  A run alone prints its lines as they are."""
    ours = _MemberStdout(sys.stdout, label, held)
    with contextlib.redirect_stdout(ours):
        try:
            yield
        finally:
            ours.end()


def say_held(held: dict[str, list[str]], once: bool = True) -> None:
    """The lines the runs of a batch said (label -> lines, :func:`member_lines` with ``held``): a
    line every run said alike (a warning about the machine, the step all resume from) once,
    with ``once``; the others, or all, each with its run's label."""
    common = set.intersection(*(set(lines) for lines in held.values())) if once and len(held) > 1 else set()
    said: set[str] = set()
    for label, lines in held.items():
        for line in lines:
            if line not in common:
                print(with_member(label, line), flush=True)
            elif line not in said:
                said.add(line)
                print(line, flush=True)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _hms(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
