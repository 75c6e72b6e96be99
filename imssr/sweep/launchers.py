"""Launchers (``imssr sweep --launcher``): each starts attempts (the same ``imssr train``
subprocess, :class:`imssr.sweep.runner.RunAttempt`) by a Ray task, a SLURM job through submitit or
the sweep itself, says which finished, hands back their results and stops what is in flight."""
from __future__ import annotations

import ipaddress
import logging
import math
import os
import shutil
import signal
import socket
import sys
import time
from dataclasses import dataclass
from typing import Any, Optional

from imssr.errors import ImssrError
from imssr.extras import require
from imssr.rundir.lock import local_holder
from imssr.sweep.directory import SweepDir
from imssr.sweep.grid import SweepConfig
from imssr.sweep.runner import STOP_GRACE_S, RunAttempt, execute_runs

# The local Ray started for a sweep only passes small results around: a small object
# store keeps its start-up memory low on small machines.
LOCAL_OBJECT_STORE_BYTES = 150 * 1024 ** 2
LOCAL_RAY_ENV = {
    # Ray's single-machine mode (its default on macOS and Windows): the node's address is
    # loopback, and every server Ray starts for it (GCS, raylet, runtime-env and dashboard
    # agents, the driver's and the workers' gRPC servers) binds to loopback alone.  Ray reads
    # this when it is imported; its processes inherit it.
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
}
SLURM_DEFAULT_MINUTES = 24 * 60
"""A SLURM job's time limit when ``--slurm-time`` is not given."""


@dataclass(frozen=True)
class Attempt:
    """What an attempt runs: ``imssr train`` of one run directory (its ``config.json``), or of
    several in one process (``imssr train --runs``), to ``steps`` agent steps."""

    run_dirs: tuple[str, ...]
    """The run directories (one unless the sweep packs runs: ``runs_per_process``)."""
    steps: int
    """The budget in agent steps that makes the run done."""
    attempt: int
    """The attempt's number (1 for the first of this sweep)."""

    def failed(self, what: str, exc: BaseException) -> list[dict]:
        """The result of each run when the attempt itself failed (``what``: the task or job) with ``exc``."""
        text = str(exc).strip().splitlines()
        error = f"{what} failed: {text[0] if text else type(exc).__name__}"
        return [{"ok": False, "error": error} for _ in self.run_dirs]


class Launcher:
    """Starts attempts and waits on them; one per sweep invocation."""

    def check(self) -> None:
        """Fail in one line if the launcher cannot work here (a missing extra), before the
        sweep writes anything."""

    def start(self) -> None:
        """Connect to what runs the attempts."""

    def capacity(self) -> int:
        """Attempts in flight at once."""
        raise NotImplementedError

    def submit(self, attempts: list[Attempt]) -> list[Any]:
        """Start ``attempts``; one handle each."""
        raise NotImplementedError

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        """The handles among ``handles`` whose attempt finished, waiting up to ``timeout_s``
        for at least one."""
        raise NotImplementedError

    def result(self, handle: Any) -> list[dict]:
        """A finished attempt's result for each of its runs (:func:`imssr.sweep.runner.execute_runs`'s
        keys); a lost worker or job is a failed attempt."""
        raise NotImplementedError

    def stop(self, handles: list[Any]) -> None:
        """Stop the attempts in flight (an interrupted sweep); each keeps its last checkpoint."""

    def shutdown(self) -> None:
        """Release what :meth:`start` took."""


def make_launcher(cfg: SweepConfig, submitit_cluster: str = "slurm") -> Launcher:
    """The launcher ``cfg.launcher`` names.  ``submitit_cluster`` picks submitit's executor for
    ``slurm`` (``local``: submitit's local executor, which runs the jobs on this machine)."""
    if cfg.launcher == "slurm":
        return SlurmLauncher(cfg, submitit_cluster)
    if cfg.launcher == "local":
        return LocalLauncher(cfg)
    return RayLauncher(cfg)


def _wait_polling(handles: list[Any], done, timeout_s: float, interval_s: float = 0.2) -> list[Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        ready = [h for h in handles if done(h)]
        if ready or time.monotonic() >= deadline:
            return ready
        time.sleep(interval_s)


class LocalLauncher(Launcher):
    """Attempts as subprocesses of the sweep: no Ray, no scheduler.  Killing the sweep (even
    with SIGKILL) kills its trainings (``PR_SET_PDEATHSIG``)."""

    def __init__(self, cfg: SweepConfig):
        self.cfg = cfg

    def capacity(self) -> int:
        fits = max(1, int((os.cpu_count() or 1) // self.cfg.cpus_per_run))
        return min(fits, self.cfg.max_parallel) if self.cfg.max_parallel else fits

    def submit(self, attempts: list[Attempt]) -> list[RunAttempt]:
        return [RunAttempt(list(a.run_dirs), a.steps, a.attempt, os.nice(0)) for a in attempts]

    def wait(self, handles: list[RunAttempt], timeout_s: float) -> list[RunAttempt]:
        return _wait_polling(handles, lambda h: h.ended, timeout_s)

    def result(self, handle: RunAttempt) -> list[dict]:
        return handle.finish_all()

    def stop(self, handles: list[RunAttempt]) -> None:
        for handle in handles:
            handle.stop()


class RayLauncher(Launcher):
    """One Ray task per attempt, on a private local Ray or the cluster at ``cfg.address``."""

    def __init__(self, cfg: SweepConfig):
        self.cfg, self.ray, self.task = cfg, None, None
        self.attempts: dict[Any, Attempt] = {}
        """The attempt of each submitted task (:meth:`stop` signals its training)."""

    def check(self) -> None:
        _import_ray(self.cfg)

    def start(self) -> None:
        cfg = self.cfg
        ray = _import_ray(cfg)
        # Workers' output goes to each run's sweep.log, not to the driver's terminal.
        common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                      configure_logging=True)
        try:
            if cfg.address:
                _check_reachable(cfg.address)
                ray.init(address=cfg.address, **common)
            else:
                # "local": always a fresh instance of our own, never a cluster that happens to run
                # on this machine (ray.init() with no address would attach to it).
                ray.init(address="local", object_store_memory=LOCAL_OBJECT_STORE_BYTES, **common)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else repr(exc)
            if not cfg.address:
                raise ImssrError(f"could not start a local Ray: {first}") from None
            # A head started by `ray start` (Ray >= 2.59) requires its token, but a driver that
            # connects by address only sends one with RAY_AUTH_MODE=token: say so in the error.
            hint = "" if os.environ.get("RAY_AUTH_MODE") == "token" else \
                " (is it running? a head started by `ray start` needs RAY_AUTH_MODE=token here too)"
            raise ImssrError(f"could not connect to the Ray cluster at {cfg.address}: {first}{hint}") from None
        # Ray binds its servers to loopback only when the node's address is loopback: a Ray that
        # took another address is stopped before it runs anything.
        node_ip = None if cfg.address else ray.util.get_node_ip_address()
        if node_ip is not None and not _is_loopback(node_ip):
            ray.shutdown()
            raise ImssrError(f"the local Ray took {node_ip} as its address instead of loopback, so it would "
                             f"listen beyond this machine; it was shut down before running anything")
        self.ray, self.task = ray, ray.remote(execute_runs).options(num_cpus=cfg.cpus_per_run,
                                                                    num_gpus=cfg.gpus_per_run, max_retries=0)

    def capacity(self) -> int:
        """Runs that fit at once in the cluster's CPUs (and GPUs when runs need them)."""
        cfg, resources = self.cfg, self.ray.cluster_resources()
        fits = int(resources.get("CPU", 1) // cfg.cpus_per_run)
        if cfg.gpus_per_run > 0:
            gpus = resources.get("GPU", 0)
            if gpus < cfg.gpus_per_run:
                raise ImssrError(f"--gpus-per-run {cfg.gpus_per_run} but the Ray cluster has {gpus:g} GPUs")
            fits = min(fits, int(gpus // cfg.gpus_per_run))
        if fits < 1:
            raise ImssrError(f"--cpus-per-run {cfg.cpus_per_run} exceeds the Ray cluster's "
                             f"{resources.get('CPU', 0):g} CPUs")
        return min(fits, cfg.max_parallel) if cfg.max_parallel else fits

    def submit(self, attempts: list[Attempt]) -> list[Any]:
        handles = [self.task.remote(list(a.run_dirs), a.steps, a.attempt, sweep_niceness(self.cfg)) for a in attempts]
        self.attempts.update(zip(handles, attempts))
        return handles

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        ready, _ = self.ray.wait(list(handles), num_returns=1, timeout=timeout_s)
        return ready

    def result(self, handle: Any) -> list[dict]:
        attempt = self.attempts.pop(handle)
        try:
            return self.ray.get(handle)
        except self.ray.exceptions.RayError as exc:
            return attempt.failed("Ray task", exc)

    def stop(self, handles: list[Any]) -> None:
        # Each training gets one SIGTERM and checkpoints where it is; wait for that before
        # ray.shutdown kills the workers.  On a private local Ray a training that holds its run's
        # lock is signalled directly; a cancel (KeyboardInterrupt inside the task) can miss the
        # wait on a loaded machine, so it serves only where the training is not ours to signal
        # or has no lock yet.  Never both: a second SIGTERM stops it without its checkpoint.
        for handle in handles:
            attempt = self.attempts.get(handle)
            run_dir = None if self.cfg.address or attempt is None else attempt.run_dirs[0]
            pid = local_holder(run_dir) if run_dir else None
            if pid is None:
                self.ray.cancel(handle, force=False)
                continue
            try:
                os.killpg(pid, signal.SIGTERM)  # a training leads its own session
            except ProcessLookupError:  # it ended meanwhile, or leads no group: the task decides
                self.ray.cancel(handle, force=False)
        if handles:
            self.ray.wait(list(handles), num_returns=len(handles), timeout=STOP_GRACE_S + 15)

    def shutdown(self) -> None:
        # Trainings still running die with their workers.
        if self.ray is not None:
            self.ray.shutdown()


class SlurmLauncher(Launcher):
    """One SLURM job per attempt through submitit, all of a round in one job array (so
    ``--slurm-array-parallelism`` bounds how many run at once); SLURM queues the rest."""

    def __init__(self, cfg: SweepConfig, cluster: str = "slurm"):
        self.cfg, self.cluster, self.executor = cfg, cluster, None
        self.attempts: dict[Any, Attempt] = {}

    def check(self) -> None:
        require("submitit", "slurm")
        if self.cluster == "slurm" and shutil.which("sbatch") is None:
            raise ImssrError("--launcher slurm needs SLURM's sbatch, which is not on PATH here; run the "
                             "sweep on a login node of the cluster (or use --launcher local or ray)")

    def start(self) -> None:
        submitit = require("submitit", "slurm")
        c = self.cfg
        self.executor = submitit.AutoExecutor(folder=os.path.join(SweepDir(c.root).submitit_dir, "%j"),
                                              cluster=self.cluster)
        params: dict[str, Any] = dict(name="imssr", timeout_min=c.slurm_time or SLURM_DEFAULT_MINUTES,
                                      cpus_per_task=max(1, math.ceil(c.cpus_per_run)), tasks_per_node=1, nodes=1)
        if self.cluster == "slurm":
            optional = {"slurm_partition": c.slurm_partition, "slurm_gpus_per_task": c.slurm_gpus_per_task}
            params.update({k: v for k, v in optional.items() if v},  # unset: the cluster's default
                          slurm_array_parallelism=c.slurm_array_parallelism or 256)
        self.executor.update_parameters(**params)

    def capacity(self) -> int:
        # Everything is submitted at once: SLURM (and the array's parallelism) schedules it.
        return 2 ** 31

    def submit(self, attempts: list[Attempt]) -> list[Any]:
        with self.executor.batch():
            jobs = [self.executor.submit(execute_runs, list(a.run_dirs), a.steps, a.attempt) for a in attempts]
        self.attempts.update(zip(jobs, attempts))
        return jobs

    def wait(self, handles: list[Any], timeout_s: float) -> list[Any]:
        # done() asks SLURM (sacct) at most every few seconds per job: submitit caches the answer.
        return _wait_polling(handles, lambda job: job.done(), timeout_s, interval_s=1.0)

    def result(self, handle: Any) -> list[dict]:
        attempt = self.attempts.pop(handle)
        try:
            return handle.result()
        except Exception as exc:  # noqa: BLE001 - a job SLURM lost, cancelled or timed out
            return attempt.failed(f"SLURM job {handle.job_id}", exc)

    def stop(self, handles: list[Any]) -> None:
        for job in handles:
            try:
                job.cancel(check=False)
            except Exception:  # noqa: BLE001 - a job that already ended
                pass


def sweep_niceness(cfg: SweepConfig) -> Optional[int]:
    """The priority a private local Ray's trainings get: this sweep's nice value (``nice -n 19
    imssr sweep``), not its workers' (Ray starts them at +15).  None on a cluster
    (``--address``): how niced the driver is says nothing about the cluster's nodes."""
    return None if cfg.address else os.nice(0)


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in one line, at once, if nothing listens at ``[ray://]HOST:PORT`` (``ray.init`` retries
    such an address for minutes); other addresses (``auto``) are left to Ray."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ImssrError(f"could not connect to the Ray cluster at {address}: nothing answers there "
                         f"({exc.strerror or exc}); start it with `ray start --head --port {port}`") from None


def _import_ray(cfg: SweepConfig):
    """``import ray``, with the environment the sweep's Ray needs set first (Ray reads it when it is
    imported, and its processes inherit it): a local Ray gets :data:`LOCAL_RAY_ENV`, and a process
    that imported ray without it fails in one line, since that ray would listen on every interface."""
    # No usage-stats prompt or upload from a batch job (and none on machines without network).
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if not cfg.address:
        missing = " ".join(f"{k}={v}" for k, v in LOCAL_RAY_ENV.items() if os.environ.get(k) != v)
        if sys.modules.get("ray") is None:  # (None too: an import of ray that is blocked)
            # The token authentication Ray gives a new local cluster anyway, stated: Ray announces the
            # mode on the sweep's output only when it chose it itself.  A mode the user set stays.
            os.environ.setdefault("RAY_AUTH_MODE", "token")
            os.environ.update(LOCAL_RAY_ENV)
        elif missing:  # ray has read its settings: set now, they would differ in the driver and Ray's processes
            raise ImssrError(f"a local sweep keeps Ray on loopback, which needs {missing} before ray is "
                             f"imported, but this process imported ray without it: set it in the environment")
    return require("ray", "sweep")


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"
