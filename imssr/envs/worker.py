"""An environment in a process of its own (``train.env_workers``).

:class:`EnvWorker` stands in for an env and forwards each call, in order, to a worker process that built the env
itself, with its own MuJoCo and EGL context.  :meth:`EnvWorker.step_async` returns at once, so a training can step
the envs of all its seeds at once, and while it updates.
"""
from __future__ import annotations

import atexit
import multiprocessing as mp
import signal
import traceback
import weakref
from typing import Any, Callable, Optional

import numpy as np

from imssr.crash import describe_exit, report_native_crashes
from imssr.errors import ImssrError

START_TIMEOUT_S = 300.0
"""How long building the env in its worker may take (importing dm_control, the EGL context)."""

_LIVE: "weakref.WeakSet[EnvWorker]" = weakref.WeakSet()
"""The workers of this process not closed yet (:func:`end_workers` ends them)."""
_AT_EXIT = False
"""Whether :func:`end_workers` is registered to run at the interpreter's exit."""


def _serve(conn, make: Callable[[], Any]) -> None:  # pragma: no cover - runs in the worker process
    # A stop signal reaches the whole process group (Ctrl-C, a sweep's SIGTERM, SLURM): the
    # training it stops still needs its envs for the checkpoint, and closes them itself.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    report_native_crashes()
    try:
        try:
            env = make()
            reply = (True, (env.action_space, env.observation_space, env.physics_state_dim))
        except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
            conn.send((False, _portable(exc)))
            return
        conn.send(reply)
        while True:
            name, args, kwargs = conn.recv()
            try:
                reply = (True, getattr(env, name)(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001
                reply = (False, _portable(exc))
            conn.send(reply)
            if name == "close":
                break
    except (EOFError, OSError):
        # The training is gone (it exited, or was killed): nobody is left to answer, and a
        # traceback of the closed pipe would only hide the training's own last line.
        pass
    finally:
        conn.close()


def _portable(exc: BaseException) -> Exception:
    """``exc`` as something that crosses a pipe: itself when it pickles (ImssrError and the
    like), else an ImssrError with its first line."""
    import pickle

    try:
        pickle.dumps(exc)
        return exc if isinstance(exc, Exception) else ImssrError(f"env worker: {type(exc).__name__}")
    except Exception:  # noqa: BLE001
        line = (str(exc).splitlines() or [type(exc).__name__])[0]
        return ImssrError(f"env worker: {line} ({traceback.format_exception_only(type(exc), exc)[-1].strip()})")


class EnvWorker:
    """``make()`` (a picklable callable that builds the env) run in a process of its own."""

    def __init__(self, make: Callable[[], Any]):
        # spawn, not fork: the parent may hold an EGL context and torch's threads.
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, make), daemon=True)
        self._proc.start()
        child.close()
        self._pending: Optional[np.ndarray] = None
        self._closed = False
        _watch(self)
        if not self._conn.poll(START_TIMEOUT_S):
            self.close()
            raise ImssrError(f"an env worker did not start in {START_TIMEOUT_S:.0f} s")
        self.action_space, self.observation_space, self.physics_state_dim = self._receive()

    def _receive(self):
        try:
            ok, value = self._conn.recv()
        except EOFError:
            raise self._died() from None
        if not ok:
            raise value
        return value

    def _died(self) -> ImssrError:
        """The one-line error for a worker whose pipe broke: how it ended (a native crash prints
        its traceback on the worker's stderr)."""
        self._proc.join(timeout=1.0)  # its pipe closes a moment before its exit status is known
        return ImssrError(f"an env worker died ({describe_exit(self._proc.exitcode)})")

    def _call(self, name: str, *args, **kwargs):
        self._settle()
        self._send((name, args, kwargs))
        return self._receive()

    def _send(self, message) -> None:
        try:
            self._conn.send(message)
        except OSError:  # a broken pipe: the worker is gone
            raise self._died() from None

    def _settle(self) -> None:
        """Take the result of a step sent and not collected (nothing may overtake it)."""
        if self._pending is not None:
            self._pending = None
            self._receive()

    def step_async(self, action: np.ndarray) -> None:
        """Send ``action``; :meth:`step` with the same action returns its result."""
        self._settle()
        self._send(("step", (action,), {}))
        self._pending = np.array(action, copy=True)

    def step(self, action: np.ndarray):
        if self._pending is not None:
            if not np.array_equal(self._pending, action):
                raise ImssrError("env worker: step with another action than the one sent ahead")
            self._pending = None
            return self._receive()
        return self._call("step", action)

    def reset(self, **kwargs):
        return self._call("reset", **kwargs)

    def physics_state(self) -> np.ndarray:
        return self._call("physics_state")

    def get_rng_state(self) -> dict:
        return self._call("get_rng_state")

    def set_rng_state(self, state: dict) -> None:
        return self._call("set_rng_state", state)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        _LIVE.discard(self)
        try:
            if self._proc.is_alive():
                if self._pending is not None and self._conn.poll(10.0):
                    self._conn.recv()  # a step sent ahead: its result would block the worker's pipe
                self._pending = None
                self._conn.send(("close", (), {}))
                self._conn.poll(10.0)
        except (OSError, EOFError):
            pass
        finally:
            self._proc.join(timeout=10.0)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
            self._conn.close()

    def end(self) -> None:
        """End the worker now (SIGKILL: it ignores the stop signals), with nothing sent or waited for."""
        self._closed = True
        _LIVE.discard(self)
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(timeout=5.0)
        self._conn.close()


def _watch(worker: EnvWorker) -> None:
    """Keep ``worker`` for :func:`end_workers`, registered at exit with the first worker: after multiprocessing's own
    handler, so it runs before that one, which would join the daemon workers (deaf to SIGTERM) without a timeout."""
    global _AT_EXIT
    if not _AT_EXIT:
        atexit.register(end_workers)
        _AT_EXIT = True
    _LIVE.add(worker)


def end_workers() -> None:
    """End every env worker of this process that is still running (:meth:`EnvWorker.end`): the
    process exits without closing them (an error, a second stop signal)."""
    for worker in list(_LIVE):
        try:
            worker.end()
        except (OSError, ValueError):  # already reaped, or its pipe already closed
            pass


def step_all(envs: list, actions: list) -> list:
    """``envs[k].step(actions[k])`` for every k, the worker envs stepping at the same time."""
    for env, action in zip(envs, actions):
        if isinstance(env, EnvWorker):
            env.step_async(action)
    return [env.step(action) for env, action in zip(envs, actions)]
