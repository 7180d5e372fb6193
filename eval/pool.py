"""Where eval's and sweep's jobs run: a local process pool (the default), or Ray tasks
inside `on_ray()` (`flowerpose eval|sweep --ray [ADDRESS]`: a local Ray without an
address, an existing cluster with one, or "auto").

Every job is one plant's work at one stage (generate, capture: scan + frames +
reconstruction, score, a sweep setting's evaluation), so the plants' scans,
reconstructions and detections overlap wherever there are cores for them. A job that
raises (on Ray, after one more try) is reported by plant and stage (`JobsFailed`, or the
bad input's own error where every failure was bad input) once every other job of the
stage has finished, so their results, written by the jobs themselves into the run's
folder and the stage cache, are kept, and the same command run again does only the rest.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import socket
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from flowerpose.errors import InputError, JobsFailed, one_line
from flowerpose.log import LOG, Tally
from flowerpose.processes import quiet_worker


@dataclass(frozen=True)
class Execution:
    """How a recipe's jobs run, beside what they run on: `workers` processes (None: one
    a core) and the stage cache's folder `cache` the captures, detections and scores are
    taken from and put into (None: every stage runs). Inside `on_ray` every job goes to
    Ray instead of the pool."""

    workers: int | None = None
    cache: Path | None = None


#: A recipe's jobs when not told: a process a core, no stage cache.
LOCAL = Execution()


#: Times a Ray task that raised is run again before it counts as failed.
TASK_RETRIES = 1

#: Environment a Ray worker needs that a cluster's own shell may not set (headless
#: rendering).
WORKER_ENVIRONMENT = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "FLOWERPOSE_CACHE")


@dataclass
class RayJobs:
    """The Ray session eval and sweep run their jobs on (inside `on_ray`)."""

    tasks_by_node: Counter = field(default_factory=Counter)
    """Finished tasks per Ray node id: where the work landed."""

    def largest_node_cpus(self) -> int:
        import ray

        return max(int(n["Resources"].get("CPU", 1)) for n in ray.nodes() if n["Alive"])


_session: RayJobs | None = None


@contextlib.contextmanager
def on_ray(address: str | None) -> Iterator[RayJobs]:
    """Run every `run_jobs` inside on Ray: a local Ray with this machine's cores when
    `address` is None, else the cluster at `address` ("auto": the one this machine
    belongs to). One line, exit 2, where Ray is not installed or not reachable."""
    global _session
    try:
        import ray
    except ModuleNotFoundError:
        raise InputError("ray", "needs the [ray] extra (ray is not installed): "
                         "pip install 'flowerpose[ray]'") from None
    if address is not None:
        _check_listening(address)
    environment = {name: os.environ[name] for name in WORKER_ENVIRONMENT if name in os.environ}
    # A local Ray is this command's own: no dashboard. A cluster keeps its own settings.
    own = {"include_dashboard": False} if address is None else {}
    try:
        ray.init(address=address, log_to_driver=False, logging_level="ERROR",
                 runtime_env={"env_vars": environment}, **own)
    except (ConnectionError, ValueError, RuntimeError) as error:
        raise InputError("ray", f"cannot reach Ray at {address or 'a local Ray'}: "
                         f"{str(error).splitlines()[0]}") from None
    session = _session = RayJobs()
    try:
        yield session
    finally:
        _session = None
        ray.shutdown()
        counts = sorted(session.tasks_by_node.values(), reverse=True)
        LOG.info(f"ray: {sum(counts)} tasks on {len(counts)} node(s) "
                 f"({', '.join(map(str, counts))})")


def _check_listening(address: str) -> None:
    """One line, at once, for a host:port where nothing listens: Ray itself retries such an
    address for minutes. "auto" and ray:// addresses are left to Ray."""
    host, _, port = address.rpartition(":")
    if "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=3.0).close()
    except OSError as error:
        raise InputError("ray", f"nothing answers at {address} ({error.strerror or error}): "
                         "start the cluster (ray start --head) or give its address") from None


def run_jobs(function: Callable, jobs: list[tuple], workers: int | None,
             describe: Callable[[int, Any], str] | None = None, *,
             stage: str = "job", labels: list[str] | None = None,
             cpus: int = 1, gpu: Literal["none", "needed", "if_any"] = "none") -> list[Any]:
    """function(*job) for every job, results in job order: in a process pool of `workers`
    (default: every core; 1 runs them here, one after another), or as Ray tasks of `cpus`
    cores each inside `on_ray` (`workers` is then Ray's to choose). With `describe`, a
    line per finished job with the time left (`log.Tally`). stage, labels: what each job
    is (the stage, and the plant of each job), for the report of a job that failed.
    gpu: on Ray, whether each task asks for a GPU: "needed" (refused in one line where the
    cluster has none, instead of waiting for ever), "if_any" (where the cluster has one)."""
    if _session is not None:
        return _run_on_ray(_session, function, jobs, describe, stage,
                           labels or [f"job {k}" for k in range(len(jobs))], cpus,
                           _task_gpus(gpu, stage))
    labels = labels or [f"job {k}" for k in range(len(jobs))]
    results: list[Any] = [None] * len(jobs)
    failures: list[tuple[str, BaseException]] = []
    pool = _pool(min(workers or os.cpu_count() or 1, len(jobs)))
    with Tally(len(jobs) if describe is not None else 0, stage) as tally:

        def settle(k: int, outcome: Callable[[], Any]) -> None:
            try:
                results[k] = outcome()
            except Exception as error:  # the job's own failure; Ctrl-C and SIGTERM go on up
                failures.append((labels[k], error))
                _say_failed(labels[k], f"{stage} failed", error, traceback=True)
                return
            if describe is not None:
                tally.finished(describe(k, results[k]))

        if pool is None:
            for k, job in enumerate(jobs):
                settle(k, lambda job=job: function(*job))
        else:
            try:
                futures = {pool.submit(function, *job): k for k, job in enumerate(jobs)}
                for future in as_completed(futures):
                    settle(futures[future], future.result)
            except BaseException:
                # Ctrl-C or SIGTERM: no new job starts, and the workers, which ignore
                # Ctrl-C, end with this process (`processes.die_with_parent`).
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
    if failures:
        raise failed(stage, failures, retried=False)
    return results


def _pool(workers: int) -> ProcessPoolExecutor | None:
    return spawn_pool(workers) if workers > 1 else None


def spawn_pool(workers: int) -> ProcessPoolExecutor:
    """A local pool of `workers` quiet worker processes (`quiet_worker`), spawned: forking a
    process that already runs Open3D's threads is unsafe."""
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=quiet_worker)


def running_on_ray() -> bool:
    """Whether jobs go to Ray now (inside `on_ray`)."""
    return _session is not None


def submit_job(pool: ProcessPoolExecutor | None, function: Callable, job: tuple,
               cpus: int = 1) -> Future:
    """function(*job) in the background, its result a Future: a Ray task of `cpus` cores
    inside `on_ray` (tried once more if it raises; the Future then holds the task's own
    exception), else in `pool`, which is then needed."""
    if _session is None:
        if pool is None:
            raise ValueError("submit_job needs a pool outside on_ray")
        return pool.submit(function, *job)
    import ray

    session = _session
    task = ray.remote(_ray_task).options(num_cpus=min(cpus, session.largest_node_cpus()),
                                         max_retries=TASK_RETRIES, retry_exceptions=True)
    result: Future = Future()

    def settle(done: Future) -> None:
        try:
            value, node = done.result()
        except ray.exceptions.RayError as error:
            result.set_exception(getattr(error, "cause", None) or error)
            return
        session.tasks_by_node[node] += 1
        result.set_result(value)

    task.remote(function, job).future().add_done_callback(settle)
    return result


def _task_gpus(gpu: str, stage: str) -> int:
    """GPUs a Ray task of `stage` asks for (`run_jobs`' gpu)."""
    if gpu == "none":
        return 0
    import ray

    available = ray.cluster_resources().get("GPU", 0)
    if gpu == "needed" and not available:
        raise InputError("ray", f"the {stage} needs a GPU (scan.reconstruct.dense_method = "
                         "patch_match) and the Ray cluster has none")
    return 1 if available else 0


def _ray_task(function: Callable, job: tuple) -> tuple[Any, str]:
    """One job in a Ray worker: its result and the node that ran it."""
    import ray

    from flowerpose.log import configure_worker

    configure_worker()
    return function(*job), ray.get_runtime_context().get_node_id()


def _run_on_ray(session: RayJobs, function: Callable, jobs: list[tuple],
                describe: Callable[[int, Any], str] | None, stage: str, labels: list[str],
                cpus: int, gpus: int = 0) -> list[Any]:
    import ray

    task = ray.remote(_ray_task).options(
        num_cpus=min(cpus, session.largest_node_cpus()), num_gpus=gpus,
        max_retries=TASK_RETRIES,
        retry_exceptions=True)
    refs = {task.remote(function, job): k for k, job in enumerate(jobs)}
    results: list[Any] = [None] * len(jobs)
    failures: list[tuple[str, BaseException]] = []
    pending = list(refs)
    with Tally(len(jobs) if describe is not None else 0, stage) as tally:
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                k = refs[done[0]]
                try:
                    results[k], node = ray.get(done[0])
                except ray.exceptions.RayError as error:
                    cause = getattr(error, "cause", None) or error
                    failures.append((labels[k], cause))
                    _say_failed(labels[k], f"{stage} failed on every try", cause)
                    continue
                session.tasks_by_node[node] += 1
                if describe is not None:
                    tally.finished(describe(k, results[k]))
        except BaseException:
            # Ctrl-C, SIGTERM: the tasks not yet done are cancelled, their workers stopped.
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    if failures:
        raise failed(stage, failures, retried=True)
    return results


def _say_failed(label: str, what: str, error: BaseException, traceback: bool = False) -> None:
    """Log a job's failure as it happens: bad input at debug level, since it is said once,
    as the command's own error line, at the end; any other as a warning. traceback: with
    it, where -v asks for debug."""
    LOG.log(logging.DEBUG if isinstance(error, InputError) else logging.WARNING,
            f"{label}: {what}: {one_line(error)}",
            exc_info=error if traceback and LOG.isEnabledFor(logging.DEBUG) else None)


def failed(stage: str, failures: list[tuple[str, BaseException]], retried: bool
           ) -> Exception:
    """What a stage whose jobs failed raises: where every failure was bad input, the first
    one's own `InputError` (one line naming its flag, exit 2, as if it had failed alone);
    else `JobsFailed`, naming each plant. retried: each failed job was tried again."""
    if all(isinstance(error, InputError) for _, error in failures):
        return failures[0][1]
    return JobsFailed(stage, failures, retried)


#: Cores a capture job (render, match, stereo: each multi-threaded) asks of a Ray node, at
#: most the largest node's.
CAPTURE_CPUS = 2


def said_steps(seconds: dict[str, float], cached: list[str]) -> str:
    """"(scan 95 s, frames 7 s, reconstruct 160 s)", naming the steps that came from the
    cache: a capture job's progress line."""
    if cached and set(seconds) <= set(cached):
        return "(from the cache)"
    return "(" + ", ".join(f"{step} from the cache" if step in cached else f"{step} {t:.0f} s"
                           for step, t in seconds.items()) + ")"
