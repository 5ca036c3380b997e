"""Campaigns of independent closed-loop scenarios, run in this process, in worker processes
(`Workers(jobs=N)`) or on a Ray cluster (`Workers(ray=...)`), with the same results
whichever runs them.

A campaign is a picklable task, called as `task(loop, index)` in a process that holds a
ClosedLoop of the campaign's scenario, and the scenario indices to run. Everything random
in scenario `index` is drawn from `scenario_seed(seed, index)`, never from a stream shared
with the scenarios before it: the results do not depend on which worker ran a scenario
or in what order.

Worker processes on Linux are forked: they inherit the parent's loop with its compiled
kernels. Other start methods and Ray's workers build the loop again from its construction
arguments (a ClosedLoop pickles as those), loading the compiled kernels from numba's disk
cache, which the parent filled when it built its own loop. Scenarios travel in batches:
about BATCHES_PER_WORKER per worker (load balance, progress), at most MAX_BATCH
scenarios each; a batch of a 1,000-scenario campaign on 2 workers holds 63 scenarios of
~50 ms each, against a few ms to hand it out and return its runs.
"""
from __future__ import annotations

import hashlib
import math
import multiprocessing
import os
import pickle
import signal
import socket
from dataclasses import dataclass

import numpy as np

LOCAL_RAY = "local"  # Workers.ray: start a Ray instance on this machine
BATCHES_PER_WORKER = 8
MAX_BATCH = 64  # scenarios per batch at most (a progress step every few seconds)
RAY_CONNECT_TIMEOUT_S = 10.0


class WorkersError(RuntimeError):
    """The workers cannot be had (a Ray cluster unreachable, Ray not installed); the message says why."""


def default_jobs() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Workers:
    """Where a campaign's scenarios run: `jobs` processes on this machine (1: in this
    process), or Ray (`ray`: LOCAL_RAY for an instance started here with `jobs` CPUs, or a
    cluster's address "host:port", whose nodes have vitreoguard installed)."""

    jobs: int = 1
    ray: str | None = None

    def __post_init__(self):
        if isinstance(self.jobs, bool) or not isinstance(self.jobs, int) or self.jobs < 1:
            raise ValueError(f"jobs must be an integer >= 1, got {self.jobs!r}")
        if self.ray is not None and not (isinstance(self.ray, str) and self.ray):
            raise ValueError(f"ray must be None, {LOCAL_RAY!r} or a cluster address 'host:port', got {self.ray!r}")

    def describe(self) -> str:
        if self.ray is None:
            return "this process" if self.jobs == 1 else f"{self.jobs} processes"
        return f"a local Ray instance ({self.jobs} CPUs)" if self.ray == LOCAL_RAY else f"the Ray cluster at {self.ray}"


def scenario_seed(seed: int, index: int) -> np.random.SeedSequence:
    """The seed of scenario `index` of a campaign seeded `seed` (both integers >= 0): its
    own stream, the same however many scenarios the campaign has."""
    return np.random.SeedSequence(int(seed), spawn_key=(int(index),))


def batches(indices: list, workers: int) -> list[list]:
    """`indices` in consecutive batches, about BATCHES_PER_WORKER per worker, at most MAX_BATCH each."""
    size = max(1, min(MAX_BATCH, math.ceil(len(indices) / (BATCHES_PER_WORKER * max(1, workers)))))
    return [list(indices[k:k + size]) for k in range(0, len(indices), size)]


def run_tasks(loop, task, indices, workers: Workers = Workers(), progress=None) -> list:
    """[task(loop, i) for i in indices], run by `workers`; `progress(done, total)` after each
    scenario (in this process) or batch (workers). WorkersError when Ray cannot be had."""
    indices = [int(i) for i in indices]
    if not indices:
        return []
    if workers.ray is not None:
        return _run_ray(loop, task, indices, workers, progress)
    if workers.jobs == 1 or len(indices) == 1:
        out = []
        for i in indices:
            out.append(task(loop, i))
            if progress is not None:
                progress(len(out), len(indices))
        return out
    return _run_pool(loop, task, indices, workers.jobs, progress)


_WORKER: dict = {}  # in a worker process: its loop and task


def _init_worker(loop, task) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's, which stops the pool
    _WORKER["loop"], _WORKER["task"] = loop, task


def _run_batch(batch: list) -> tuple[list, list]:
    loop, task = _WORKER["loop"], _WORKER["task"]
    return batch, [task(loop, i) for i in batch]


def _context():
    """Fork where there is fork (the loop and its kernels inherited); the default elsewhere."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else None)


def _run_pool(loop, task, indices: list, jobs: int, progress) -> list:
    parts = batches(indices, jobs)
    results, done = {}, 0
    # leaving the block by any exit (Ctrl-C included) terminates the workers
    with _context().Pool(min(jobs, len(parts)), initializer=_init_worker, initargs=(loop, task)) as pool:
        for batch, res in pool.imap_unordered(_run_batch, parts):
            results.update(zip(batch, res))
            done += len(batch)
            if progress is not None:
                progress(done, len(indices))
    return [results[i] for i in indices]


def _ray_module():
    try:
        import ray
    except ImportError:
        raise WorkersError("--ray needs the ray package (pip install ray)") from None
    return ray


def _check_reachable(address: str) -> None:
    """WorkersError unless a TCP connection to the address 'host:port' opens within
    RAY_CONNECT_TIMEOUT_S (ray.init itself retries for minutes)."""
    host, sep, port = address.rpartition(":")
    if address == "auto":
        return
    if not sep or not host or not port.isdigit():
        raise WorkersError(f"--ray: the address must be host:port (the cluster head's GCS port), got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=RAY_CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise WorkersError(f"--ray {address}: no Ray cluster reachable there ({exc.strerror or exc})") from None


def connect_ray(workers: Workers) -> None:
    """Join (or start, for LOCAL_RAY) the Ray instance of `workers` unless this process is
    connected already; WorkersError when it cannot."""
    ray = _ray_module()
    if workers.ray != LOCAL_RAY:
        _check_reachable(workers.ray)
    if ray.is_initialized():
        return
    if workers.ray == LOCAL_RAY:
        ray.init(num_cpus=workers.jobs, include_dashboard=False, log_to_driver=False, configure_logging=False)
        return
    try:
        ray.init(address=workers.ray, log_to_driver=False, configure_logging=False)
    except Exception as exc:  # ray raises ConnectionError, RuntimeError, ValueError by version
        raise WorkersError(f"--ray {workers.ray}: cannot join the Ray cluster: {str(exc).splitlines()[0]}") from None


class _RayRunner:
    """A Ray actor (a process of its own) that runs batches of a task on a loop. The loop is
    built once per construction (its pickled bytes' digest) and kept for the campaigns
    after it on the same loop; the task comes with each campaign. Both travel pickled as
    bytes: Ray's own arrays would arrive read-only."""

    def __init__(self):
        self.loop_key, self.loop, self.task = None, None, None

    def prepare(self, loop_key: str, loop_blob: bytes, task_blob: bytes) -> None:
        if loop_key != self.loop_key:
            self.loop, self.loop_key = pickle.loads(loop_blob), loop_key
        self.task = pickle.loads(task_blob)

    def run(self, batch: list) -> tuple[list, list]:
        return batch, [self.task(self.loop, i) for i in batch]


_RAY_ACTORS: dict = {"job": None, "actors": []}  # this process's actors in its Ray job, reused by every campaign


def _ray_actors(ray, n: int) -> list:
    """n actors of this process's Ray job (started once: a new actor is a new process
    that imports everything and loads the compiled kernels again)."""
    job = ray.get_runtime_context().get_job_id()
    if _RAY_ACTORS["job"] != job:  # another Ray job (ray.init again): the old handles are gone
        _RAY_ACTORS.update(job=job, actors=[])
    actors = _RAY_ACTORS["actors"]
    runner = ray.remote(num_cpus=1)(_RayRunner)
    actors += [runner.remote() for _ in range(n - len(actors))]
    return actors[:n]


def _run_ray(loop, task, indices: list, workers: Workers, progress) -> list:
    connect_ray(workers)
    ray = _ray_module()
    cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    parts = batches(indices, workers.jobs if workers.ray == LOCAL_RAY else cpus)
    loop_blob = pickle.dumps(loop, protocol=pickle.HIGHEST_PROTOCOL)
    key = hashlib.sha256(loop_blob).hexdigest()
    loop_ref, task_ref = ray.put(loop_blob), ray.put(pickle.dumps(task, protocol=pickle.HIGHEST_PROTOCOL))
    actors = _ray_actors(ray, min(len(parts), cpus))
    ray.get([a.prepare.remote(key, loop_ref, task_ref) for a in actors])
    results, done, pending, queue = {}, 0, {}, list(reversed(parts))
    try:
        for actor in actors:  # two batches in flight per actor: one runs while the next is sent
            for _ in range(2):
                if queue:
                    pending[actor.run.remote(queue.pop())] = actor
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            actor = pending.pop(ready[0])
            batch, res = ray.get(ready[0])
            results.update(zip(batch, res))
            done += len(batch)
            if progress is not None:
                progress(done, len(indices))
            if queue:
                pending[actor.run.remote(queue.pop())] = actor
    except BaseException:  # Ctrl-C or a failed batch: stop the work in flight
        for actor in _RAY_ACTORS["actors"]:
            ray.kill(actor)
        _RAY_ACTORS["actors"] = []
        raise
    return [results[i] for i in indices]
