"""Hostile inputs of an independent round before issue 47's (found outside the repository, kept here as generated variants)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kiloforge import numfmt
from kiloforge.actors.dense import dense_weights

_RNG = np.random.default_rng(np.random.SeedSequence(20261206))
#: (e_in, e_out, f): a zero weight row whose bias lands at -(2^31 + f * 2^(shift-1)), where the rounding constant
#: would bring |b + 2^(shift-1)| back under 2^31 although b itself is no int32
BIAS_EDGE = [(int(_RNG.integers(0, 8)), int(_RNG.integers(0, 8)), float(_RNG.uniform(0.01, 0.99))) for _ in range(8)]


@pytest.mark.parametrize("e_in,e_out,f", BIAS_EDGE)
def test_bias_beyond_int32_is_never_wrapped(e_in, e_out, f):
    """A bias just beyond int32 next to all-zero weights is rescaled (or refused), never wrapped to the other sign."""
    W = np.zeros((2, 5))
    W[1] = np.linspace(-1.0, 1.0, 5)
    shift_max = numfmt.MAX_SHIFT
    b = np.array([-(2.0 ** 31 + f * 2.0 ** (shift_max - 1)) / 2.0 ** (shift_max + e_out), 0.1])
    wq, bq, shift, e = dense_weights("layer", W, b, e_in, e_out, may_lower_e_out=True)
    assert bq[0] < 0
    assert int(numfmt.acc_bound(wq, bq, shift).max()) < numfmt.ACC32_LIMIT
    np.testing.assert_allclose(bq[0] * 2.0 ** -(int(shift[0]) + e), b[0], rtol=1e-6)


# --- a user's task (--task file.py:Class): what its code raises or returns is one line -----------------------
_TASK = """import numpy as np
from sim.tasks.localisation import Localisation
class T(Localisation):
    name = "hostile"
{body}
"""
_HOOK_ARGS = {"world": "self, cfg", "spawn": "self, env", "step_info": "self, env", "reward": "self, env, u, info",
              "state": "self, env", "state_dim": "self, cfg, n", "episode_metrics": "self, *a, **k",
              "has_ceiling": "self, cfg", "bound_report": "self, cfg"}
_BAD_BODIES = ["raise ValueError('bad\\nvalue')", "raise ZeroDivisionError", "raise KeyError('k')", "assert False, 'no'",
               "return None", "return 'text'", "return np.full((7, 3), np.nan)"]
#: (hook, body): every hook with each way of failing, plus returns of the right kind but wrong content
TASK_HOOKS = [(h, b) for h in _HOOK_ARGS for b in _BAD_BODIES] + [
    ("spawn", "b, p, h = super().spawn(env)\n        return b, p * 1e6, h"),
    ("spawn", "b, p, h = super().spawn(env)\n        return b, p[:, :1], h"),
    ("spawn", "b, p, h = super().spawn(env)\n        return None, p, h"),
    ("reward", "return np.full(env.n_envs, np.inf)"), ("state_dim", "return -1"), ("state_dim", "return True"),
    ("step_info", "return {1: np.zeros(env.n_envs)}"),
]
TASK_ATTRS = ["metrics = 5", "metrics = ()", "metrics = ('final_success',)", "features = 'wall'", "features = (1, 2)",
              "beacon = 1", "description = None", "baselines = {'random': 3}", "success_label = b'x'",
              "success_plot = '../x'", "success_plot = 3",
              "@property\n    def metrics(self):\n        raise RuntimeError('m')"]
TASK_IMPORTS = ["raise SystemExit(7)", "import sys\nsys.exit('bye')", "class E(BaseException): pass\nraise E('x')",
                "raise GeneratorExit", "x = 1\x00", "raise ValueError('a\\rb\\x1b[2J')"]


def _hostile_task(tmp_path, source: str):
    from sim.tasks import get_task

    f = tmp_path / "t.py"
    f.write_text(source)
    return get_task(f"{f}:T")


def _exercise(task) -> None:
    from sim.config import preset
    from sim.env import SwarmEnv

    cfg = task.world(preset("kilobot"))
    env = SwarmEnv(cfg, 1, 3, seed=0, task=task)
    env.reset()
    env.step(np.full((1, 3, 2), 0.5))
    env.state()
    task.episode_metrics(cfg, 3, np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 2)))
    task.has_ceiling(cfg)
    task.bound_report(cfg)


def _one_line(excinfo, *words: str) -> None:
    msg = str(excinfo.value)
    assert "\n" not in msg and "\r" not in msg and all(w in msg for w in words), msg


@pytest.mark.parametrize("hook,body", TASK_HOOKS)
def test_task_hook_failure_is_one_line(tmp_path, hook, body):
    """A user task's hook that raises or returns the wrong kind of value is one InputError naming the hook."""
    from kiloforge.errors import InputError

    task = _hostile_task(tmp_path, _TASK.format(body=f"    def {hook}({_HOOK_ARGS[hook]}):\n        {body}\n"))
    with pytest.raises(InputError) as e:
        _exercise(task)
    _one_line(e, f"{hook}()", "t.py:T")


@pytest.mark.parametrize("attr", TASK_ATTRS)
def test_task_attribute_of_the_wrong_kind_is_one_line(tmp_path, attr):
    """A user task's attribute of the wrong type, or one that raises, is refused when the task is loaded."""
    from kiloforge.errors import InputError

    with pytest.raises(InputError) as e:
        _hostile_task(tmp_path, _TASK.format(body=f"    {attr}\n"))
    _one_line(e, "t.py:T")


@pytest.mark.parametrize("code", TASK_IMPORTS)
def test_task_file_that_exits_or_raises_while_importing_is_one_line(tmp_path, code):
    """A task file that exits, or raises a BaseException, at import is one InputError, not the end of the command."""
    from kiloforge.errors import InputError

    with pytest.raises(InputError) as e:
        _hostile_task(tmp_path, code + "\n")
    _one_line(e, "t.py")


def test_guarded_user_task_still_runs(tmp_path):
    """The guard changes nothing for a well-behaved user task: same episode as its unguarded class."""
    from sim.tasks.localisation import Localisation

    task = _hostile_task(tmp_path, _TASK.format(body="    pass\n"))
    assert isinstance(task, Localisation) and task.name == "hostile"
    _exercise(task)


# --- an output path that names a device, a named pipe or a socket --------------------------------------------
def _special(tmp_path, kind: str):
    import os
    import socket

    target = tmp_path / f"special-{kind}"
    if kind.endswith("fifo"):
        os.mkfifo(target)
    else:
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(target))
        s.close()
    if kind.startswith("link"):
        (tmp_path / "link").symlink_to(target)
        return tmp_path / "link", target
    return target, target


SPECIAL = ["fifo", "socket", "link-fifo", "link-socket"]


#: a set of files replaces a link among its names (never follows it), so only the one-file writers meet a linked one
SPECIAL_WRITES = [(w, k) for w in ("write_atomic", "atomic_path", "write_files_atomic") for k in SPECIAL
                  if not (w == "write_files_atomic" and k.startswith("link"))]


@pytest.mark.parametrize("writer,kind", SPECIAL_WRITES)
def test_special_file_is_never_replaced(tmp_path, writer, kind):
    """A write to a named pipe or socket (or a link to one) is one OutputError and leaves it as it was (as root,
    the same write would have turned /dev/null into a regular file)."""
    import stat

    from kiloforge import io as kio
    from kiloforge.errors import OutputError

    path, target = _special(tmp_path, kind)
    before = target.lstat()
    with pytest.raises(OutputError, match="not a regular file"):
        if writer == "write_atomic":
            kio.write_atomic(path, b"x")
        elif writer == "atomic_path":
            with kio.atomic_path(path) as tmp:
                tmp.write_bytes(b"x")
        else:
            kio.write_files_atomic({path: b"x", tmp_path / "record.json": b"{}"})
    after = target.lstat()
    assert stat.S_IFMT(after.st_mode) == stat.S_IFMT(before.st_mode) and after.st_ino == before.st_ino
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted({path.name, target.name})


@pytest.mark.parametrize("kind", SPECIAL[:2])
def test_rehash_and_export_refuse_a_special_out(tmp_path, capsys, kind):
    """`export rehash --out` and `export --out` at a named pipe or socket: exit 2, one line, nothing replaced."""
    import shutil

    from export.cli.main import main

    path, target = _special(tmp_path, kind)
    src = tmp_path / "p.npz"
    shutil.copy(Path(__file__).parents[1] / "export" / "data" / "default_policy.npz", src)
    out = tmp_path / "k.c"
    for argv in (["rehash", str(src), "--out", str(path)],
                 ["--out", str(out), "--robots-calib", "2", "--calib-steps", "4", "--quiet", "--no-avr"]):
        if argv[0] == "--out":
            target.rename(out)
            target = out
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "not a regular file" in err, err
        assert not target.is_file()


# --- ONNX: no file beside the model is opened -------------------------------------------------------------
BESIDE = ["{}.world.json", "{}.world.json->secret", "{}.world.json->/dev/zero"]


@pytest.mark.parametrize("beside", BESIDE)
def test_onnx_never_opens_a_world_json_beside_the_model(tmp_path, monkeypatch, capsys, beside):
    """A model without metadata is refused asking for --world-json, even with a (planted, valid or linked)
    <model>.world.json beside it; that file is never opened."""
    import builtins
    import json
    import os

    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    from export.cli.main import main
    from sim.config import preset

    d = preset("kilobot").history_dim(2)
    inits = [numpy_helper.from_array(np.zeros((d, 2), np.float32), "w")]
    g = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", d])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 2])], inits)
    model = tmp_path / "actor.onnx"
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]), str(model))
    name, _, link = beside.partition("->")
    planted = tmp_path / name.format("actor")
    if not link:
        planted.write_text(json.dumps({"world": "kilobot", "t_prev": 2}))
    else:
        secret = tmp_path / "secret" if link == "secret" else Path(link)
        if link == "secret":
            secret.write_text(json.dumps({"world": "kilobot", "t_prev": 2}))
        planted.symlink_to(secret)
    opened = []
    real_open = os.open

    def spy(path, *a, **k):
        opened.append(os.fspath(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(os, "open", spy)
    monkeypatch.setattr(builtins, "open", lambda f, *a, **k: (opened.append(os.fspath(f)), io_open(f, *a, **k))[1])
    capsys.readouterr()
    rc = main(["--onnx", str(model), "--out", str(tmp_path / "k.c"), "--robots-calib", "2", "--calib-steps", "4",
               "--quiet", "--no-avr"])
    err = capsys.readouterr().err
    assert rc == 2 and "--world-json" in err and len(err.strip().splitlines()) == 1, err
    assert not [p for p in opened if "world.json" in p or p.endswith("secret")], opened
    assert not (tmp_path / "k.c").exists()


io_open = open


# --- a run folder never makes `learn plot` import code --------------------------------------------------------
PLANTED_SPECS = ["{d}/evil.py:T", "run/evil.py:T", "./run/evil.py:T", "{d}/evil.py:Missing", "{d}/a:b/evil.py:T",
                 "run/../run/evil.py:T"]
NEAR = Path(__file__).parent / "tasks" / "near_beacon.py"


def _run_folder(tmp_path, task: str, column: str) -> Path:
    import json

    run = tmp_path / "run"
    run.mkdir(exist_ok=True)
    (run / "config.json").write_text(json.dumps({"exp_name": "x", "algorithm": "es", "task": task, "n_robots": 4,
                                                 "t_prev": 2}))
    (run / "metrics.csv").write_text(f"env_steps,eval_return,{column}\n100,1.5,0.25\n200,2.5,0.5\n")
    return run


@pytest.mark.parametrize("spec", PLANTED_SPECS)
def test_plot_never_imports_a_task_file_a_run_folder_names(tmp_path, monkeypatch, capsys, spec):
    """`learn plot` of a run whose config.json names a task file: one line asking for --task, the file never runs."""
    from kiloforge.cli import main

    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "ran"
    spec = spec.format(d=tmp_path)
    run = _run_folder(tmp_path, spec, "eval_final_success")
    evil = Path(spec.rpartition(":")[0])
    evil = evil if evil.is_absolute() else tmp_path / evil
    evil.parent.mkdir(parents=True, exist_ok=True)
    evil.write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    capsys.readouterr()
    assert main(["plot", str(run), "--out", str(tmp_path / "lc.png")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and ("--task" in err or "unknown task" in err), err
    assert not marker.exists() and not (tmp_path / "lc.png").exists()


def test_plot_of_a_task_file_run_with_the_users_task(tmp_path, monkeypatch, capsys):
    """With --task given by the user, a run of a task file plots its own primary metric column."""
    from kiloforge.cli import main

    run = _run_folder(tmp_path, f"{NEAR}:NearBeacon", "eval_final_near")
    assert main(["plot", str(run), "--out", str(tmp_path / "lc.png"), "--task", f"{NEAR}:NearBeacon"]) == 0
    assert (tmp_path / "lc.png").stat().st_size > 0


# --- standard streams closed by the caller (`>&-`, `2>&-`) ----------------------------------------------------
CLOSED_STREAM_CMDS = [["--version"], ["export", "budget", "--history", "20"], ["sim", "--version"],
                      ["export", "--out", "k.c", "--robots-calib", "2", "--calib-steps", "4", "--no-avr", "--quiet"]]


@pytest.mark.parametrize("closed", [(1,), (1, 2), (0, 1)])
@pytest.mark.parametrize("cmd", CLOSED_STREAM_CMDS)
def test_closed_standard_streams_are_one_line(tmp_path, cmd, closed):
    """A command whose standard output (and maybe input or error) was closed: never a traceback; with standard
    error open, exit 0 or one line and exit 2; no file the command writes takes a closed descriptor's number."""
    import os
    import subprocess
    import sys

    root = Path(__file__).parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    res = subprocess.run([sys.executable, "-m", "kiloforge", *cmd], cwd=tmp_path, env=env, stderr=subprocess.PIPE,
                         preexec_fn=lambda: [os.close(fd) for fd in closed], timeout=300)
    err = res.stderr.decode()
    assert "Traceback" not in err, err
    if 2 not in closed:
        lines = err.strip().splitlines()
        assert (res.returncode, lines) == (0, []) or (res.returncode == 2 and len(lines) == 1
                                                       and "standard output" in err), (res.returncode, err)
    for f in tmp_path.iterdir():  # nothing a tool printed ended up inside an output
        assert b"wrote " not in f.read_bytes()
