"""Where benchmark jobs run: a local process pool, or Ray (local instance or a cluster).

Both engines have the same small interface, driven by :mod:`dynastereo.bench.runner`:
``submit(job)``, ``poll(timeout) -> [Event]``, ``capacity`` (jobs worth keeping in flight),
``close()``.  An :class:`Event` is ``("progress", key, frames_done)``, ``("done", key,
record)`` or ``("failed", key, error)``; a job whose worker process dies (killed, out of
memory, a segfault in a native library) is ``"failed"`` with the exit reason, and the
worker is replaced.  Retrying is the driver's business, not the engine's.

* :class:`LocalEngine` -- ``workers`` processes started with ``spawn`` (no forked threads
  or native state), each single-threaded (:func:`~dynastereo.bench.jobs.set_single_thread`)
  and running one job at a time; each has its own pipe, so the driver always knows which
  job a dead worker was running.  (``concurrent.futures.ProcessPoolExecutor`` cannot: one
  dead worker breaks the whole pool and fails every job in flight.)  Workers import
  dynastereo once and run many jobs.
* :class:`RayEngine` -- one Ray task per job (``num_cpus=1``, ``max_retries=0``).  Without
  ``address`` a local Ray instance with ``num_cpus=workers`` is started (and stopped at
  the end); with ``address`` (``ray://host:10001`` or ``host:6379``, or ``auto``) the
  driver joins that cluster.  Results come back as task return values (the record with
  the small output files); frame progress through a ``ray.util.queue.Queue``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

from ..errors import DynastereoError
from .jobs import THREAD_ENV, BenchJob, error_text, execute, set_single_thread

PROGRESS_INTERVAL_S = 0.25


@dataclass(frozen=True)
class Event:
    kind: str  # progress | done | failed
    key: str
    value: Any


def _death_reason(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"WorkerDied: the worker process was killed by {name}"
    return f"WorkerDied: the worker process exited with code {exitcode}"


class _Throttle:
    """Calls ``send(done)`` at most every PROGRESS_INTERVAL_S, and always for the last frame."""

    def __init__(self, send) -> None:
        self.send, self.last = send, 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done >= total or now - self.last >= PROGRESS_INTERVAL_S:
            self.last = now
            self.send(done)


@contextmanager
def _environment(values: dict[str, str]):
    """``os.environ`` with ``values`` set, restored afterwards (for child processes to inherit)."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# --------------------------------------------------------------------------- local


def _local_worker(conn: Connection) -> None:
    """A worker process: jobs in, progress and records out, until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle
    set_single_thread()
    while True:
        job = conn.recv()
        if job is None:
            return
        try:
            rec = execute(job, _Throttle(lambda d, k=job.key: conn.send(("progress", k, d))))
            conn.send(("done", job.key, rec))
        except BaseException as e:  # noqa: BLE001 -- reported to the driver, which retries
            conn.send(("failed", job.key, error_text(e)))


class _Worker:
    def __init__(self, ctx) -> None:
        self.conn, child = ctx.Pipe(duplex=True)
        with _environment(THREAD_ENV):  # inherited by the spawned interpreter before any import
            self.proc = ctx.Process(target=_local_worker, args=(child,), daemon=True, name="dynastereo-bench")
            self.proc.start()
        child.close()
        self.job: BenchJob | None = None


class LocalEngine:
    name = "local"

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise DynastereoError(f"--workers must be >= 1, got {workers}")
        self._ctx = mp.get_context("spawn")
        self._workers = [_Worker(self._ctx) for _ in range(workers)]
        self.capacity = workers
        self.description = f"local process pool, {workers} workers"

    def submit(self, job: BenchJob) -> None:
        i = next((i for i, w in enumerate(self._workers) if w.job is None), None)
        if i is None:
            raise RuntimeError("no idle worker (the driver keeps at most `capacity` jobs in flight)")
        if not self._workers[i].proc.is_alive():  # died while idle (e.g. the OOM killer): replace it
            self._workers[i].conn.close()
            self._workers[i] = _Worker(self._ctx)
        w = self._workers[i]
        w.job = job
        try:
            w.conn.send(job)
        except OSError:
            pass  # it died just now: poll() reports the job failed and replaces the worker

    def poll(self, timeout: float) -> list[Event]:
        busy = [w for w in self._workers if w.job is not None]
        if not busy:
            time.sleep(min(timeout, 0.05))
            return []
        ready = set(wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout))
        events: list[Event] = []
        for i, w in enumerate(self._workers):
            if w.job is None:
                continue
            if w.conn in ready:
                try:
                    while w.conn.poll():
                        kind, key, value = w.conn.recv()
                        events.append(Event(kind, key, value))
                        if kind != "progress":
                            w.job = None
                except (EOFError, OSError):
                    pass
            if w.job is not None and not w.proc.is_alive():
                w.proc.join()
                events.append(Event("failed", w.job.key, _death_reason(w.proc.exitcode)))
                w.conn.close()
                self._workers[i] = _Worker(self._ctx)
        return events

    def close(self) -> None:
        for w in self._workers:
            if w.job is None and w.proc.is_alive():
                try:
                    w.conn.send(None)
                except OSError:
                    pass
        deadline = time.monotonic() + 5.0
        for w in self._workers:
            if w.job is not None:
                w.proc.terminate()
            w.proc.join(max(0.0, deadline - time.monotonic()))
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join()
            w.conn.close()


# --------------------------------------------------------------------------- Ray


def _ray_task(job: BenchJob, queue) -> dict[str, Any]:
    set_single_thread()

    def send(done: int) -> None:
        try:
            queue.put_nowait(("progress", job.key, done))
        except Exception:  # noqa: BLE001 -- progress is best effort
            pass

    return execute(job, _Throttle(send))


class RayEngine:
    name = "ray"

    def __init__(self, workers: int, address: str | None = None) -> None:
        try:
            import ray
            from ray.util.queue import Queue
        except ImportError:
            raise DynastereoError("--engine ray needs Ray: pip install 'dynastereo[bench]' (or: pip install ray)") \
                from None
        self._ray = ray
        if address:
            # a cluster's workers get the single-thread environment through the runtime env
            ray.init(address=address, runtime_env={"env_vars": dict(THREAD_ENV)}, log_to_driver=False,
                     logging_level="WARNING")
            cpus = int(ray.cluster_resources().get("CPU", 1))
            self.description = f"Ray cluster at {address}, {cpus} CPUs"
        else:
            if workers < 1:
                raise DynastereoError(f"--workers must be >= 1, got {workers}")
            # a local instance's workers inherit the driver's environment: set, start, restore
            # (no runtime_env, so the workers Ray starts with the instance take the first jobs)
            # usage statistics off unless asked for: a benchmark (and CI) makes no calls home
            env = {**THREAD_ENV, "RAY_USAGE_STATS_ENABLED": os.environ.get("RAY_USAGE_STATS_ENABLED", "0")}
            with _environment(env):
                # address="local": a new instance even when RAY_ADDRESS or a `ray start` cluster exists
                ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False,
                         logging_level="WARNING")
            cpus = workers
            self.description = f"local Ray instance, {workers} CPUs"
        self.capacity = max(1, cpus)
        self._queue = Queue(actor_options={"num_cpus": 0})
        self._remote = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
        self._refs: dict[Any, str] = {}

    def submit(self, job: BenchJob) -> None:
        self._refs[self._remote.remote(job, self._queue)] = job.key

    def poll(self, timeout: float) -> list[Event]:
        ray = self._ray
        events: list[Event] = []
        if self._refs:
            ready, _ = ray.wait(list(self._refs), num_returns=len(self._refs), timeout=timeout)
        else:
            time.sleep(min(timeout, 0.05))
            ready = []
        try:
            for kind, key, done in self._queue.get_nowait_batch(self._queue.qsize()):
                events.append(Event(kind, key, done))
        except Exception:  # noqa: BLE001 -- progress is best effort
            pass
        for ref in ready:
            key = self._refs.pop(ref)
            try:
                events.append(Event("done", key, ray.get(ref)))
            except ray.exceptions.RayTaskError as e:
                cause = e.cause if getattr(e, "cause", None) is not None else e
                events.append(Event("failed", key, error_text(cause)))
            except ray.exceptions.RayError as e:  # worker crashed / killed / node lost
                first = str(e).strip().splitlines()[0] if str(e).strip() else ""
                events.append(Event("failed", key, f"WorkerDied: {type(e).__name__}: {first}"))
        return events

    def close(self) -> None:
        ray = self._ray
        for ref in list(self._refs):
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001
                pass
        self._refs.clear()
        ray.shutdown()


def make_engine(name: str, workers: int, address: str | None = None):
    if name == "local":
        if address:
            raise DynastereoError("--address is for --engine ray")
        return LocalEngine(workers)
    if name == "ray":
        return RayEngine(workers, address)
    raise DynastereoError(f"--engine must be local or ray, got {name!r}")
