"""Evaluating an ES generation's population: in this process, or on Ray workers, with the same bits.

A generation's population is the antithetic pairs θ ± σ ε_i, i < ``pairs``, with ε drawn from the
generation's own seed (:func:`noise`). A *fitness* object (:class:`Fitness`: picklable, the same in
every process) gives the fitness of any block of members on one *part* of the task (a swarm size),
playing every member on the same episodes, drawn from the generation's seed (common random numbers).
A member's fitness therefore depends on its weights and the seed only, never on which block or
process played it, and a run learns the same weights bit for bit with any number of workers.

* :class:`LocalPool` (``--workers 1``, no Ray imported): all members in one batch, part after part,
  stopping between parts when a stop was requested.
* :class:`RayPool` (``--workers N`` starts a private local Ray with N CPUs; ``--ray-address`` joins a
  cluster): N actors, one CPU each, warmed before the first generation (:meth:`RayPool.warm`). Each
  part's members are cut into N contiguous blocks and every (part, block) goes to the next idle actor.
  What travels with each block is θ, σ, the generation's seed and the block bounds (θ as the call's argument: Ray
  sends one under 100 KB inside the call, cheaper than a ``ray.put`` and a fetch from its object store, and a
  larger one through the store); every actor draws ε itself from the seed, and fetches the fitness once. A block whose
  actor dies is given again, to the next idle actor (Ray restarts the dead one, which is probed until it
  answers), at most :data:`MAX_TRIES` times. A stop request is looked at every :data:`POLL_S` seconds
  and abandons the generation. Ray starts quietly (no dashboard, workers' output not forwarded) and is
  shut down when the pool closes, also on errors and signals; on SIGKILL of the trainer its workers,
  raylet and GCS die with it (Ray's fate sharing) and its two agent processes exit on their own within
  about a minute.
"""
from __future__ import annotations

import logging
import signal
import socket
import threading
import time
from collections import deque
from typing import Callable, Protocol

import numpy as np
import torch

from kiloforge.errors import KiloforgeError

from .config import ConfigError

MAX_TRIES = 3  #: a block is given to workers at most this many times (each time one died running it)
POLL_S = 0.2  #: seconds between two looks at a stop request while workers run (and between probes of a restarting one)
RESTART_S = 600.0  #: an actor that is not back this long after it failed ends the run (with an error)
RESUME_HINT = "the run directory keeps its last checkpoint, if any (--resume continues it)"


class WorkersFailed(KiloforgeError):
    """The workers cannot evaluate a generation (a block killed its worker MAX_TRIES times, or a worker did not
    come back); the trainer stops without writing, so the last checkpoint stands."""
RAY_HINT = "pip install 'kiloforge[sweep]'"  #: what installs Ray (pyproject.toml)


class Fitness(Protocol):
    """What a member's fitness is; picklable, so that every worker holds the same object."""

    parts: int  #: independent parts of the fitness (e.g. swarm sizes), evaluated separately

    def __call__(self, members: torch.Tensor, part: int, seed: np.random.SeedSequence) -> np.ndarray:
        """members (k, P) float64 -> fitness (k,) on ``part``, its episodes drawn from ``seed``."""


class Stop(Protocol):
    def check(self) -> None:
        """Raise when a stop was requested."""


def child(ss: np.random.SeedSequence, *key: int) -> np.random.SeedSequence:
    """The child of ``ss`` at ``key``, independent of how many children were drawn before."""
    return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + tuple(key))


def noise(seed: np.random.SeedSequence, pairs: int, n_params: int) -> torch.Tensor:
    """The generation's directions ε (pairs, n_params), float64, drawn from ``seed``'s child 0."""
    rng = np.random.default_rng(child(seed, 0))
    return torch.from_numpy(rng.standard_normal((pairs, n_params)))


def members(theta: torch.Tensor, sigma: float, eps: torch.Tensor, start: int, stop: int) -> torch.Tensor:
    """Rows ``start:stop`` of the population [θ + σ ε_0, ..., θ + σ ε_{n-1}, θ − σ ε_0, ..., θ − σ ε_{n-1}]."""
    n = eps.shape[0]
    plus = theta + sigma * eps[min(start, n):min(stop, n)]
    minus = theta - sigma * eps[max(start - n, 0):max(stop - n, 0)]
    return torch.cat([plus, minus])


def blocks(k: int, n: int) -> list[tuple[int, int]]:
    """``k`` members cut into at most ``n`` contiguous blocks of near-equal size.

    >>> blocks(16, 3)
    [(0, 6), (6, 11), (11, 16)]
    >>> blocks(2, 4)
    [(0, 1), (1, 2)]
    """
    n = max(1, min(n, k))
    edges = [round(i * k / n) for i in range(n + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _evaluate_block(fitness: Fitness, theta: torch.Tensor, sigma: float, pairs: int, seed: np.random.SeedSequence,
                    part: int, start: int, stop: int) -> np.ndarray:
    """Fitness (stop − start,) of members ``start:stop`` of the generation on ``part``."""
    eps = noise(seed, pairs, theta.numel())
    return np.asarray(fitness(members(theta, sigma, eps, start, stop), part, seed), np.float64)


class LocalPool:
    """Every member in this process, one batch per part (``--workers 1``)."""

    workers = 1
    start_s = 0.0

    def warm(self, fitness: Fitness, theta: torch.Tensor) -> None:
        """Nothing to start: this process is warm once the run has evaluated its weights."""

    def evaluate(self, fitness: Fitness, theta: torch.Tensor, sigma: float, pairs: int,
                 seed: np.random.SeedSequence, stop: Stop) -> np.ndarray:
        """Fitness (2 · pairs, parts) of the generation ``seed`` around ``theta``; a stop request between parts
        abandons it (``stop.check()`` raises)."""
        out = np.empty((2 * pairs, fitness.parts))
        for part in range(fitness.parts):
            out[:, part] = _evaluate_block(fitness, theta, sigma, pairs, seed, part, 0, 2 * pairs)
            stop.check()
        return out

    def close(self) -> None:
        pass

    def __enter__(self) -> "LocalPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Worker:
    """A Ray actor: one CPU, torch on ``threads`` threads, evaluating blocks of members.

    The fitness comes as its object reference in a list, which Ray hands over unresolved: the actor fetches it on
    its first block (and after a restart) and keeps it, so a block does not unpickle the fitness again, and the
    fitness keeps what it caches (its resolved task)."""

    def __init__(self, threads: int) -> None:
        torch.set_num_threads(max(1, threads))
        self._fitness: tuple[str, Fitness] | None = None  # (its object id, the fitness)

    def ready(self) -> int:
        import os

        return os.getpid()

    def evaluate(self, fitness_ref: list, theta: torch.Tensor, sigma: float, pairs: int, seed: np.random.SeedSequence,
                 part: int, start: int, stop: int) -> np.ndarray:
        ref = fitness_ref[0]
        if self._fitness is None or self._fitness[0] != ref.hex():
            import ray

            self._fitness = (ref.hex(), ray.get(ref))
        return _evaluate_block(self._fitness[1], theta, sigma, pairs, seed, part, start, stop)


def import_ray():
    """The ``ray`` module; one-line ConfigError saying what to install when it is missing."""
    try:
        import ray
    except ModuleNotFoundError as e:
        if (e.name or "").partition(".")[0] != "ray":
            raise
        raise ConfigError(f"--workers above 1 and --ray-address evaluate on Ray, which is not installed: {RAY_HINT}") \
            from None
    return ray


def unreachable(address: str, timeout: float = 5.0) -> str | None:
    """Why nothing answers at a ``HOST:PORT`` address (None when something does, or for ``auto`` and
    ``ray://`` addresses): ``ray.init`` would retry an unreachable head for minutes."""
    host, sep, port = address.rpartition(":")
    if not sep or "://" in address or not port.isdigit():
        return None
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        return e.strerror or str(e)
    return None


def init_ray(ray, address: str, num_cpus: int | None, flag: str) -> None:
    """Start a private local Ray with ``num_cpus`` CPUs (None: all), or join the cluster at ``address`` (given as
    ``flag``), quietly (no dashboard, workers' output not forwarded), keeping this process's SIGINT and SIGTERM
    handlers: ``ray.init`` installs a SIGTERM handler that exits at once, which would skip the checkpoint and
    the exit status 143 of an interrupted run."""
    problem = unreachable(address)
    if problem:
        raise ConfigError(f"cannot reach a Ray cluster at {flag} {address}: {problem}")
    main = threading.current_thread() is threading.main_thread()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)} if main else {}
    kw = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        if address:
            ray.init(address=address, **kw)
        else:
            ray.init(address="local", num_cpus=num_cpus, **kw)
    except ConnectionError as e:
        raise ConfigError(f"cannot reach a Ray cluster at {flag} {address}: {str(e).splitlines()[0]}") from None
    except SystemExit:  # Ray's own SIGTERM handler, while it started
        from kiloforge.interrupts import Interrupted

        raise Interrupted(signal.SIGTERM) from None
    finally:
        for s, h in handlers.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)


class RayPool:
    """``workers`` Ray actors evaluating blocks of members (see the module doc)."""

    def __init__(self, workers: int, address: str = "", threads: int = 1, log: Callable[[str], None] = print) -> None:
        ray = self.ray = import_ray()
        problem = unreachable(address)  # checked even when this process's Ray is running already (which is used)
        if problem:
            raise ConfigError(f"cannot reach a Ray cluster at --ray-address {address}: {problem}")
        self.workers, self.log = workers, log
        self.own = not ray.is_initialized()  # a Ray started (or joined) here is shut down here
        self.actors: list = []
        self._fitness: Fitness | None = None
        self._fitness_ref = None
        self._restarting: dict = {}
        t0 = time.perf_counter()
        try:
            if self.own:
                init_ray(ray, address, workers, "--ray-address")
            actor = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=0)(_Worker)
            self.actors = [actor.remote(threads or 1) for _ in range(workers)]
            self.pids = ray.get([a.ready.remote() for a in self.actors])
        except BaseException:
            self.close()
            raise
        self.start_s = time.perf_counter() - t0  #: seconds to start Ray and the workers, and to warm them

    def warm(self, fitness: Fitness, theta: torch.Tensor) -> None:
        """Every worker plays one member on every part once (its first call loads the simulator's compiled code
        and torch's kernels, seconds that belong to the start-up, not to a generation); the results are dropped."""
        t0 = time.perf_counter()
        self._fitness, self._fitness_ref = fitness, self.ray.put(fitness)
        seed = np.random.SeedSequence(0)
        calls = [(a, a.evaluate.remote([self._fitness_ref], theta, 0.0, 1, seed, part, 0, 1))
                 for a in self.actors for part in range(fitness.parts)]
        for actor, ref in calls:
            try:
                self.ray.get(ref)
            except self.ray.exceptions.RayActorError:  # died: restarted by Ray, probed before it gets members
                now = time.monotonic()
                self._restarting[actor] = (now, now)
        self.start_s += time.perf_counter() - t0

    def evaluate(self, fitness: Fitness, theta: torch.Tensor, sigma: float, pairs: int,
                 seed: np.random.SeedSequence, stop: Stop) -> np.ndarray:
        """Fitness (2 · pairs, parts), the same bits as :meth:`LocalPool.evaluate`; a stop request abandons the
        generation (``stop.check()`` raises; the blocks still running are dropped when the pool closes)."""
        ray = self.ray
        if fitness != self._fitness:  # the same fitness (equal fields) travels once
            self._fitness, self._fitness_ref = fitness, ray.put(fitness)
        out = np.full((2 * pairs, fitness.parts), np.nan)
        todo = deque((part, a, b) for part in range(fitness.parts) for a, b in blocks(2 * pairs, self.workers))
        deaths = {item: 0 for item in todo}
        restarting = self._restarting  # actor -> (when it failed, when to probe it next); kept between generations
        idle = [a for a in self.actors if a not in restarting]
        running: dict = {}  # ref -> (actor, its block; None for a probe of a restarting actor)
        while todo or any(item is not None for _, item in running.values()):
            now = time.monotonic()
            for actor, (since, probe_at) in list(restarting.items()):
                if now - since > RESTART_S:
                    raise WorkersFailed(f"an ES worker did not come back within {RESTART_S:g} s of failing; "
                                        + RESUME_HINT)
                if now >= probe_at and all(act is not actor for act, _ in running.values()):
                    running[actor.ready.remote()] = (actor, None)
            while todo and idle:
                item, actor = todo.popleft(), idle.pop(0)
                running[actor.evaluate.remote([self._fitness_ref], theta, sigma, pairs, seed, *item)] = (actor, item)
            if not running:  # every actor restarting, none due for a probe yet
                time.sleep(POLL_S)
                stop.check()
                continue
            done, _ = ray.wait(list(running), num_returns=1, timeout=POLL_S)
            stop.check()
            for ref in done:
                actor, item = running.pop(ref)
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayActorError as e:  # its process died: Ray restarts it, we probe it
                    restarting[actor] = (restarting.get(actor, (time.monotonic(),))[0], time.monotonic() + POLL_S)
                    if item is None:
                        continue
                    part, a, b = item
                    deaths[item] += 1
                    if deaths[item] >= MAX_TRIES:
                        raise WorkersFailed(f"ES workers died {MAX_TRIES} times evaluating members {a}..{b - 1} "
                                            f"(part {part}), the last time: {str(e).splitlines()[0]}; "
                                            + RESUME_HINT) from None
                    self.log(f"a Ray worker died evaluating members {a}..{b - 1}; they run again")
                    todo.appendleft(item)
                    continue
                restarting.pop(actor, None)
                idle.append(actor)
                if item is not None:
                    part, a, b = item
                    out[a:b, part] = value
        return out

    def close(self) -> None:
        """Shut the Ray started here down (its workers with it); on a Ray that was running already, end the actors."""
        ray = self.ray
        if self.own:
            if ray.is_initialized():
                ray.shutdown()
        else:
            for a in self.actors:
                ray.kill(a)
        self.actors = []

    def __enter__(self) -> "RayPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def worker_pool(workers: int, address: str = "", threads: int = 1,
                log: Callable[[str], None] = print) -> LocalPool | RayPool:
    """:class:`LocalPool` for one worker and no cluster address, else :class:`RayPool`."""
    if workers == 1 and not address:
        return LocalPool()
    return RayPool(workers, address, threads, log)
