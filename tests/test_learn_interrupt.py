"""Interrupted and damaged runs: SIGINT/SIGTERM checkpoint and exit 130/143, restarts, truncated files, orphans."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learn.__main__ import main  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402

from tests import kill_harness as kh  # noqa: E402
from tests.signal_delivery import deliver  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--world", "thesis", "--robots", "2", "--history", "3", "--episode-steps", "20", "--actor-hidden", "8", "--critic-hidden", "16",
        "--n-envs", "2", "--warmup-episodes", "2", "--batch-size", "8", "--replay-size", "400",
        "--updates-per-step", "0.5", "--eval-every", "40", "--eval-episodes", "2", "--quiet"]


def _start(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "learn", *args], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 240.0) -> None:
    t0 = time.time()
    while not path.exists():
        assert proc.poll() is None, f"the run ended early: {proc.communicate()}"
        assert time.time() - t0 < timeout, f"{path} did not appear"
        time.sleep(0.2)


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_checkpoints_and_exits_128_plus_signal(tmp_path, sig, status):
    """A signal mid-run: exit 128 + signal, a checkpoint at an episode boundary holding the learning so far,
    summary 'interrupted'; --resume continues from it."""
    out = tmp_path / "run"
    proc = _start(["train", *TINY, "--episodes", "100000", "--out", str(out)])
    _wait_for(out / "metrics.csv", proc)
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == status, err
    ck = load_checkpoint(out)
    c = ck["counters"]
    assert c["env_steps"] == c["episodes"] * 20 and c["episodes"] % 2 == 0  # whole episode batches only
    assert json.loads((out / "summary.json").read_text())["stopped"] == "interrupted"
    done = c["episodes"]
    assert main(["train", "--out", str(out), "--resume", "--quiet", "--episodes", str(done + 4 - 2)]) == 0
    assert load_checkpoint(out)["counters"]["episodes"] == done + 4


def test_interrupted_before_the_first_checkpoint_restarts(tmp_path, capsys):
    """SIGINT during behaviour cloning: exit 130 and no checkpoint; the run directory refuses a plain restart
    with a hint, and --resume restarts it from scratch."""
    out = tmp_path / "run"
    proc = _start(["train", *TINY, "--episodes", "4", "--demo-policy", "searcher", "--demo-episodes", "4",
                   "--bc-updates", "1000000", "--out", str(out)])
    t0 = time.time()
    line = ""
    while "demonstrations:" not in line:  # cloning has started
        line = proc.stdout.readline()
        assert line or proc.poll() is None, proc.communicate()
        assert time.time() - t0 < 240
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=240)
    assert proc.returncode == 130
    assert (out / "config.json").is_file() and not (out / "checkpoint.pt").exists()
    assert main(["train", *TINY, "--episodes", "4", "--out", str(out)]) == 2
    assert "--resume restarts it" in capsys.readouterr().err
    assert main(["train", "--out", str(out), "--resume", "--quiet", "--bc-updates", "3"]) == 0
    assert "restarting it from scratch" in capsys.readouterr().out
    assert load_checkpoint(out)["counters"]["episodes"] == 6


def test_truncated_or_altered_checkpoint_is_one_line(tmp_path, capsys):
    """A truncated checkpoint.pt or replay block, or an altered byte, is refused with one line and exit 2;
    orphan temporary files and unreferenced blocks are removed when a run resumes."""
    out = tmp_path / "run"
    assert main(["train", *TINY, "--episodes", "2", "--out", str(out)]) == 0
    ck, block = out / "checkpoint.pt", next((out / "replay").iterdir())
    good_ck, good_block = ck.read_bytes(), block.read_bytes()
    for path, data, words in ((ck, good_ck[:-100], "truncated"), (block, good_block[:200], "truncated"),
                              (block, good_block[:-1] + bytes([good_block[-1] ^ 1]), "does not match its hash"),
                              (ck, b"not a checkpoint", "not a kiloforge checkpoint")):
        path.write_bytes(data)
        capsys.readouterr()
        assert main(["train", "--out", str(out), "--resume", "--quiet", "--episodes", "4"]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1 and "Traceback" not in err, err
        ck.write_bytes(good_ck)
        block.write_bytes(good_block)
    orphans = [out / ".checkpoint.pt.abc.tmp", out / "replay" / "g0_b0_999.pt", out / "replay" / ".g0_b1_7.pt.x.tmp"]
    for p in orphans:
        p.write_bytes(b"x")
    assert main(["train", "--out", str(out), "--resume", "--quiet", "--episodes", "4"]) == 0
    assert not any(p.exists() for p in orphans)


def test_evaluate_error_leaves_no_output_directory(tmp_path, capsys):
    """`learn evaluate` failing mid-way (too many robots for the arena) exits 2 and creates no --out."""
    out = tmp_path / "run"
    assert main(["train", *TINY, "--episodes", "0", "--world", "kilobot", "--out", str(out)]) == 0
    ev = tmp_path / "sub" / "eval"
    assert main(["evaluate", "--policy", str(out / "policy_best.npz"), "--robots", "2", "1000", "--episodes", "1",
                 "--steps", "5", "--n-envs", "1", "--no-gif", "--out", str(ev), "--quiet"]) == 2
    assert "spawn area" in capsys.readouterr().err
    assert not ev.exists() and not ev.parent.exists() and not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize("algorithm", ["magddpg", "magrdpg"])
def test_sigint_mid_episode_resumes_to_the_uninterrupted_run(tmp_path, monkeypatch, algorithm):
    """SIGINT in the middle of a learning episode batch that no evaluation ends: the batch is finished and
    checkpointed (exit 130); resuming gives the uninterrupted run's networks, optimisers, replay, RNG streams
    and metrics rows bit for bit (MLP and GRU)."""
    import learn.groups as groups
    from learn.config import RecurrentConfig, TrainConfig
    from learn.train import train

    tiny = dict(world="thesis", n_robots=2, episode_steps=20, n_envs=2, warmup_episodes=2, episodes=10, eval_every=120,
                eval_episodes=2, replay_size=400, seed=6, threads=1)
    cfg = (TrainConfig(**tiny, t_prev=3, actor_hidden=(8,), critic_hidden=(16,), batch_size=8, updates_per_step=0.5)
           if algorithm == "magddpg" else
           RecurrentConfig(**tiny, batch_windows=4, unroll=4, burn_in=3, hidden=6, critic_hidden=(16,)))
    quiet = lambda m: None  # noqa: E731
    full = train(cfg, tmp_path / "full", progress=False, log=quiet)
    real, calls = groups.EnvGroup.step, []

    def interrupting(self):
        calls.append(1)
        if len(calls) == 3 * 20 + 7:  # step 7 of batch 4 (of 5): evaluations end batches 1, 3 and 5
            deliver(signal.SIGINT)
        return real(self)

    monkeypatch.setattr(groups.EnvGroup, "step", interrupting)
    cut = train(cfg, tmp_path / "cut", progress=False, log=quiet)
    monkeypatch.setattr(groups.EnvGroup, "step", real)
    assert cut.stopped == "interrupted" and cut.exit_status == 130 and len(calls) == 4 * 20
    ck = load_checkpoint(tmp_path / "cut")
    assert ck["counters"]["episodes"] == 8 and ck["counters"]["evals"] == 2 and ck["counters"]["pending_losses"]
    train(cfg, tmp_path / "cut", resume=True, progress=False, log=quiet)
    a, b = load_checkpoint(tmp_path / "full"), load_checkpoint(tmp_path / "cut")
    for part in ("actor", "critic", "actor_target", "critic_target"):
        for k in a["agent"][part]:
            torch.testing.assert_close(a["agent"][part][k], b["agent"][part][k], rtol=0, atol=0)
    for k in a["agent"]["critic_opt"]["state"]:
        torch.testing.assert_close(a["agent"]["critic_opt"]["state"][k]["exp_avg_sq"],
                                   b["agent"]["critic_opt"]["state"][k]["exp_avg_sq"], rtol=0, atol=0)
    torch.testing.assert_close(a["replay"][0]["tuples"], b["replay"][0]["tuples"], rtol=0, atol=0)
    assert all(a["rng"][k] == b["rng"][k] for k in ("env", "noise", "replay", "augment", "demo"))
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    rows_a = [{k: v for k, v in r.items() if k not in kh.TIMING} for r in a["counters"]["rows"]]
    rows_b = [{k: v for k, v in r.items() if k not in kh.TIMING} for r in b["counters"]["rows"]]
    assert len(rows_a) == 3 and np.array_equal(rows_array(rows_a), rows_array(rows_b), equal_nan=True)
    assert full.counters.updates == load_checkpoint(tmp_path / "cut")["counters"]["updates"]


def rows_array(rows: list[dict]) -> np.ndarray:
    """Metrics rows as one float array (columns in a fixed order), NaN kept."""
    keys = sorted(rows[0])
    return np.array([[float(r[k]) for k in keys] for r in rows])
