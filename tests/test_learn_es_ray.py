"""ES on Ray workers (learn.es_pool): the same weights for any worker count, a dead worker's members run again,
Ctrl-C checkpoints and resumes exactly, Ray's processes end with the run, a missing Ray is one line."""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("ray")

from kiloforge.policies import load_policy  # noqa: E402
from learn.__main__ import main  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.config import ESConfig  # noqa: E402
from learn.es_pool import LocalPool, RayPool, blocks, members, noise  # noqa: E402
from learn.es_train import train_es  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: a run of a few seconds whose fitness differs between members (so the weights move)
SMALL = dict(n_robots=(2, 3), t_prev=2, actor_hidden=(8,), episode_steps=100, demo_policy="none", generations=3,
             pairs=3, eval_every=3, eval_episodes=1, eval_steps=20, threads=1, seed=2)
SMALL_FLAGS = ["--robots", "2", "3", "--history", "2", "--actor-hidden", "8", "--episode-steps", "100",
               "--demo-policy", "none", "--pairs", "3", "--eval-episodes", "1", "--eval-steps", "20", "--threads", "1",
               "--seed", "2"]


def _quiet(_msg: str) -> None:
    pass


def _theta(run_dir: Path) -> torch.Tensor:
    return load_checkpoint(run_dir / "checkpoint.pt")["theta"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The in-process run (--workers 1) of SMALL, the weights every worker count must reach."""
    out = tmp_path_factory.mktemp("reference") / "run"
    train_es(ESConfig(**SMALL), out, progress=False, log=_quiet)
    return out


def test_members_and_blocks_cover_the_population():
    """Blocks of members put together are the whole antithetic population [θ + σε, θ − σε], row for row."""
    theta = torch.randn(5, dtype=torch.float64)
    eps = noise(np.random.SeedSequence(3), 4, 5)
    whole = torch.cat([theta + 0.1 * eps, theta - 0.1 * eps])
    for n in (1, 2, 3, 8, 20):
        parts = blocks(8, n)
        assert parts[0][0] == 0 and parts[-1][1] == 8 and all(a < b for a, b in parts)
        assert all(parts[i][1] == parts[i + 1][0] for i in range(len(parts) - 1))
        assert torch.equal(torch.cat([members(theta, 0.1, eps, a, b) for a, b in parts]), whole)


def test_two_workers_learn_the_same_weights(ray_session, reference, tmp_path):
    """--workers 2 ends with exactly the weights of --workers 1 (the weights moved), says its block size, and the
    summary has the generations and their seconds."""
    first = train_es(ESConfig(**{**SMALL, "generations": 1}), tmp_path / "first", progress=False, log=_quiet)
    said: list[str] = []
    res = train_es(ESConfig(**SMALL, workers=2), tmp_path / "two", progress=False, log=said.append)
    assert any(m.startswith("evaluating the population on 2 Ray workers, in blocks of 3 members") for m in said), said
    assert res.stopped == "done"
    want = _theta(reference)
    assert torch.equal(_theta(tmp_path / "two"), want)
    assert not torch.equal(_theta(first.run_dir), want)  # the members' fitness differed: the weights moved
    a, b = load_policy(reference / "policy_last.npz"), load_policy(tmp_path / "two" / "policy_last.npz")
    for x, y in zip(a.weights + a.biases, b.weights + b.biases, strict=True):
        np.testing.assert_array_equal(x, y)
    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["generations"] == 3 and summary["workers"] == 2 and 0 < summary["generation_s"] <= summary["wall_s"]


def _worker_pids(title: bytes) -> list[int]:
    """Processes whose title (Ray sets it to ray::<class>.<method> while an actor runs a method) starts with ``title``."""
    pids = []
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                with open(f"/proc/{p}/cmdline", "rb") as f:
                    if f.read().startswith(title):
                        pids.append(int(p))
            except OSError:
                pass
    return pids


def test_a_killed_worker_has_its_members_run_again(ray_session, reference, tmp_path, monkeypatch):
    """SIGKILL of a worker in the middle of evaluating members: they run again and the weights are the
    uninterrupted run's."""
    killed, done, warmed = [], threading.Event(), threading.Event()
    warm = RayPool.warm

    def warm_then_say(self, *args):
        warm(self, *args)
        warmed.set()

    monkeypatch.setattr(RayPool, "warm", warm_then_say)  # the kill is to land in a generation, after the warm-up

    def killer():
        warmed.wait(240)
        seen: dict[int, int] = {}
        while not done.is_set() and not killed:
            ours = _descendants(os.getpid())  # this session's Ray only, not another job's on the same machine
            for pid in (p for p in _worker_pids(b"ray::_Worker.evaluate") if p in ours):
                seen[pid] = seen.get(pid, 0) + 1
                if seen[pid] >= 3:  # busy for a few polls: inside a block, not finishing one
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    break
            time.sleep(0.05)

    lines: list[str] = []
    t = threading.Thread(target=killer)
    t.start()
    try:
        train_es(ESConfig(**SMALL, workers=2), tmp_path / "run", progress=False, log=lines.append)
    finally:
        done.set()
        t.join()
    assert killed, "no worker was seen evaluating"
    assert any("a Ray worker died" in line for line in lines), lines
    assert torch.equal(_theta(tmp_path / "run"), _theta(reference))


def _descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                with open(f"/proc/{p}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(p))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_ctrl_c_with_workers_checkpoints_and_resumes_exactly(ray_session, reference, tmp_path):
    """Ctrl-C (SIGINT to the process group) during a --workers 2 run: exit 130, a checkpoint of a finished
    generation, no Ray process left; --resume ends with the uninterrupted run's weights."""
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "learn", "train-es", *SMALL_FLAGS, "--generations", "3",
                             "--eval-every", "1", "--workers", "2", "--quiet", "--out", str(out)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0 = time.time()
    while not _worker_pids(b"ray::_Worker.evaluate") or not (out / "metrics.csv").exists():
        assert proc.poll() is None, f"the run ended early: {proc.communicate()}"
        assert time.time() - t0 < 240, "no worker started evaluating"
        time.sleep(0.05)
    ray_procs = _descendants(proc.pid)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    ck = load_checkpoint(out / "checkpoint.pt")
    assert ck["es_generation"] < 3
    assert json.loads((out / "summary.json").read_text())["stopped"] == "interrupted"
    deadline = time.time() + 30
    while any(map(_alive, ray_procs)) and time.time() < deadline:
        time.sleep(0.2)
    assert ray_procs and not any(map(_alive, ray_procs)), "Ray processes outlived the run"
    assert main(["train-es", "--out", str(out), "--resume", "--quiet", "--workers", "2"]) == 0
    assert load_checkpoint(out / "checkpoint.pt")["es_generation"] == 3
    assert torch.equal(_theta(out), _theta(reference))


def test_local_pool_stops_between_parts():
    """The in-process pool looks at the stop request after each part and raises there."""
    class Stop:
        def __init__(self):
            self.calls = 0

        def check(self):
            self.calls += 1
            if self.calls == 1:
                raise KeyboardInterrupt

    class Parts:
        parts = 2
        played: list = []

        def __call__(self, m, part, seed):
            self.played.append(part)
            return np.zeros(len(m))

    fit = Parts()
    with pytest.raises(KeyboardInterrupt):
        LocalPool().evaluate(fit, torch.zeros(3, dtype=torch.float64), 0.1, 2, np.random.SeedSequence(1), Stop())
    assert fit.played == [0]


def test_missing_ray_is_one_line(tmp_path, capsys, monkeypatch):
    """--workers 2 without Ray installed: one line naming what to pip install, exit 2, nothing written;
    --workers 1 runs without it."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ModuleNotFoundError
    assert main(["train-es", *SMALL_FLAGS, "--generations", "1", "--quiet", "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()
    assert main(["train-es", *SMALL_FLAGS, "--workers", "2", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'kiloforge[sweep]'" in err[0], err
    assert not (tmp_path / "r").exists()


def test_unreachable_ray_address_is_one_line(tmp_path, capsys):
    """--ray-address where no Ray head listens: one line naming the address, exit 2, nothing written."""
    import socket

    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["train-es", *SMALL_FLAGS, "--ray-address", f"127.0.0.1:{port}", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--ray-address 127.0.0.1:{port}" in err[0], err
    assert not (tmp_path / "r").exists()



def test_a_block_that_kills_its_worker_every_time_stops_the_run(ray_session, tmp_path):
    """A task whose members kill their Ray worker each time: after MAX_TRIES deaths WorkersFailed, a one-line
    KiloforgeError (the CLI prints it as one line, exit 2) that says how to resume."""
    from kiloforge.errors import KiloforgeError
    from learn.es_pool import MAX_TRIES, WorkersFailed
    from learn.es_train import actor_algo, get_theta, task_fitness
    from learn.es import PopulationMLP
    from learn.interrupt import StopRequest

    task = tmp_path / "dying.py"
    task.write_text("import os\nfrom sim.tasks.aggregation import Aggregation\n\n\n"
                    "class Dying(Aggregation):\n    name = 'dying'\n\n"
                    "    def spawn(self, env):\n"
                    f"        if os.getpid() != {os.getpid()}:  # in a Ray worker\n"
                    "            os._exit(1)\n"
                    "        return super().spawn(env)\n")
    cfg = ESConfig(**SMALL, task=f"{task}:Dying")
    world = cfg.world_config()
    algo = actor_algo(cfg, world)
    fitness = task_fitness(cfg, world, PopulationMLP.of(algo.actor.net), [None] * len(cfg.n_robots))
    with RayPool(1, log=_quiet) as pool, StopRequest() as stop, pytest.raises(WorkersFailed) as e:
        pool.evaluate(fitness, get_theta(algo), cfg.sigma, cfg.pairs, np.random.SeedSequence(0), stop)
    assert isinstance(e.value, KiloforgeError) and "\n" not in str(e.value)
    assert f"died {MAX_TRIES} times" in str(e.value) and "--resume" in str(e.value)
