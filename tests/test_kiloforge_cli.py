"""The ``kiloforge`` command (kiloforge.cli): dispatch to sim / learn / export, --version, one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import kiloforge
from kiloforge.cli import COMMANDS, learn_script, main
from kiloforge.extras import missing_dependency
from kiloforge.cliparse import invoked_as, program

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--robots-calib", "2", "3", "--calib-steps", "5", "--quiet"]
#: run the kiloforge command in a fresh interpreter with torch unimportable (``import torch`` raises
#: ModuleNotFoundError) and report whether anything imported it
NO_TORCH = ("import sys; sys.modules['torch'] = None; from kiloforge.cli import main; rc = main(sys.argv[1:]); "
            "assert 'torch' not in [m.partition('.')[0] for m in sys.modules if sys.modules[m] is not None]; "
            "sys.exit(rc)")

#: ``python -m learn ARGS`` in a fresh interpreter without the learn extra (torch, tyro, tensorboard unimportable)
NO_LEARN_EXTRA = ("import runpy, sys; sys.modules.update(torch=None, tyro=None, tensorboard=None); "
                  "sys.argv = ['learn', *sys.argv[1:]]; runpy.run_module('learn', run_name='__main__', alter_sys=True)")
#: a tiny evaluation of the shipped default policy
TINY_EVAL = ["--policy", str(ROOT / "export" / "data" / "default_policy.npz"), "--robots", "4", "--episodes", "2",
             "--steps", "20", "--n-envs", "2", "--no-gif", "--quiet", "--out", "ev"]


def kiloforge_run(args, cwd, code=None, timeout=300) -> subprocess.CompletedProcess:
    """``python -m kiloforge ARGS`` (or ``python -c CODE ARGS``) in ``cwd`` with the repository on PYTHONPATH."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "kiloforge"] if code is None else [sys.executable, "-c", code]
    return subprocess.run([*cmd, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def test_version_prints_package_version(tmp_path):
    """`kiloforge --version` prints kiloforge.__version__ and exits 0."""
    r = kiloforge_run(["--version"], tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == f"kiloforge {kiloforge.__version__}" and r.stderr == ""


def test_help_lists_every_subcommand(capsys):
    """`kiloforge --help` lists sim, learn, export and every other sub-command, exit 0."""
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert {"sim", "learn", "export"} <= set(COMMANDS)
    for name in COMMANDS:
        assert f"\n  {name} " in out


@pytest.mark.parametrize("command", ["train", "train-es"])
def test_training_help_into_a_closed_pipe_exits_quietly(tmp_path, command):
    """`python -m learn train --help | head -1`: a reader that has gone away ends the help with exit 0, no traceback."""
    r, w = os.pipe()
    os.close(r)  # every write of the help meets a closed pipe, as after `head -1` exits
    try:
        p = subprocess.run([sys.executable, "-m", "learn", command, "--help"], stdout=w, stderr=subprocess.PIPE,
                           cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)}, text=True, timeout=120)
    finally:
        os.close(w)
    assert p.returncode == 0 and p.stderr == ""


def test_unknown_subcommand_is_one_line(tmp_path):
    """An unknown sub-command is one error line naming it, exit 2."""
    r = kiloforge_run(["frobnicate", "--x"], tmp_path)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "'frobnicate'" in r.stderr and "Traceback" not in r.stderr


def test_export_from_temp_dir_like_python_dash_m(tmp_path):
    """`kiloforge export --out X.c` in an empty directory writes the same C file as `python -m export`, without torch."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    r = kiloforge_run(["export", "--out", "kp.c", *FAST], a, code=NO_TORCH)
    assert r.returncode == 0, r.stderr
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r2 = subprocess.run([sys.executable, "-m", "export", "--out", "kp.c", *FAST], cwd=b, env=env,
                        capture_output=True, text=True, timeout=300)
    assert r2.returncode == 0, r2.stderr
    assert (a / "kp.c").read_bytes() == (b / "kp.c").read_bytes()
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())


def test_sim_help_without_torch(tmp_path):
    """`kiloforge sim --help` prints sim's options with torch unimportable, and never imports it."""
    r = kiloforge_run(["sim", "--help"], tmp_path, code=NO_TORCH)
    assert r.returncode == 0, r.stderr
    assert "--robots" in r.stdout and "kiloforge sim" in r.stdout


def test_learn_train_without_torch_is_one_line(tmp_path):
    """`kiloforge learn train` with torch missing is the one install-hint line, exit 2, nothing written."""
    code = "import sys; sys.modules['torch'] = None; from kiloforge.cli import main; sys.exit(main(sys.argv[1:]))"
    r = kiloforge_run(["learn", "train", "--out", "run"], tmp_path, code=code)
    assert r.returncode == 2
    assert r.stderr == "kiloforge learn needs torch: pip install 'kiloforge[learn]'\n"
    assert list(tmp_path.iterdir()) == []


def test_abbreviated_option_refused(capsys):
    """An abbreviated option (`--rob` for `--robots`) is an error under kiloforge, not silently expanded."""
    with pytest.raises(SystemExit) as e:
        main(["learn", "evaluate", "--policy", "p.npz", "--out", "o", "--rob", "4"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "--rob" in err and err.startswith("kiloforge learn evaluate: error: ")


@pytest.mark.parametrize("module_form,name,default,expected", [
    ("python -m learn", "kiloforge learn", "python -m learn train", "kiloforge learn train"),
    ("python -m learn train", "kiloforge train", "python -m learn train", "kiloforge train"),
    ("python -m export", "kiloforge export", "python -m exporter", "python -m exporter"),
    ("python -m sim", "kiloforge sim", "kiloforge sim evaluate", "kiloforge sim evaluate"),
])
def test_program_names(module_form, name, default, expected):
    """program() renames only the python -m form the running sub-command stands for."""
    assert program(default) == default
    with invoked_as(module_form, name):
        assert program(default) == expected
    assert program(default) == default


def test_stray_module_in_working_directory_is_named(tmp_path):
    """Under `python -m kiloforge`, a sim.py in the working directory is one error line naming it, exit 2."""
    (tmp_path / "sim.py").write_text("raise SystemExit('the stray sim.py ran')\n")
    r = kiloforge_run(["sim", "--help"], tmp_path)
    assert r.returncode == 2 and r.stdout == "" and r.stderr.count("\n") == 1
    assert "sim.py" in r.stderr and "replaces kiloforge's 'sim' package" in r.stderr


def _assert_tiny_evaluation(r: subprocess.CompletedProcess, out: Path) -> None:
    """The TINY_EVAL run succeeded and wrote its results and plots."""
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and "wrote" in r.stdout
    ev = json.loads((out / "evaluation.json").read_text())
    assert ev["episodes"] == 2 and ev["steps"] == 20 and set(ev["robots"]) == {"4"}
    assert {"data/default_policy", "hand-written", "random"} <= set(ev["robots"]["4"]["metrics"])
    assert (out / "coverage_4.png").is_file() and (out / "returns_box_4.png").is_file()


def test_learn_evaluate_without_learn_extra(tmp_path):
    """`python -m learn evaluate` of the shipped .npz policy runs with torch, tyro and tensorboard unimportable."""
    r = kiloforge_run(["evaluate", *TINY_EVAL], tmp_path, code=NO_LEARN_EXTRA)
    _assert_tiny_evaluation(r, tmp_path / "ev")


def test_learn_evaluate_without_out_prints_tables_and_writes_nothing(tmp_path):
    """`python -m learn evaluate` without --out prints each size's table, exit 0, and leaves no file anywhere."""
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    r = subprocess.run([sys.executable, "-c", NO_LEARN_EXTRA, "evaluate", *TINY_EVAL[:-2]], cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(scratch)},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "4 robots, 20 steps, 2 episodes" in r.stdout and "hand-written" in r.stdout
    assert r.stdout.rstrip().endswith("nothing written (--out DIR writes evaluation.json, plots and a GIF)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scratch"] and list(scratch.iterdir()) == []


def test_kiloforge_evaluate_never_imports_torch(tmp_path):
    """`kiloforge evaluate` of the shipped .npz policy succeeds with torch unimportable and never imports it."""
    r = kiloforge_run(["evaluate", *TINY_EVAL], tmp_path, code=NO_TORCH)
    _assert_tiny_evaluation(r, tmp_path / "ev")


@pytest.mark.parametrize("args, prog", [(["train", "--out", "run"], "python -m learn"),
                                        (["train-es", "--out", "run"], "python -m learn")])
def test_python_m_learn_train_without_learn_extra_is_one_line(tmp_path, args, prog):
    """`python -m learn train` (and train-es) without the learn extra is one install-hint line, exit 2."""
    r = kiloforge_run(args, tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(f"{prog} needs ")
    assert r.stderr.endswith(": pip install 'kiloforge[learn]'\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("module, line", [
    ("torch", "p needs torch: pip install 'kiloforge[learn]'"),
    ("onnx.helper", "p needs onnx: pip install 'kiloforge[onnx]'"),
    ("ray", "p needs ray: pip install 'kiloforge[sweep]'"),
    ("pettingzoo", "p needs pettingzoo: pip install 'kiloforge[pettingzoo]'"),
    ("PIL", "p needs PIL (a dependency of kiloforge): pip install pillow"),
    ("matplotlib.pyplot", "p needs matplotlib (a dependency of kiloforge): pip install matplotlib"),
    ("left_pad", None),
])
def test_missing_dependency_line(module, line):
    """A missing optional or core dependency is one line naming what to pip install; an unknown module is None."""
    assert missing_dependency("p", ModuleNotFoundError(f"No module named '{module}'", name=module)) == line


def test_console_script_without_torch_is_one_line(tmp_path, monkeypatch, capsys):
    """The kiloforge-learn console script prints the install hint (exit 2) when torch is missing."""
    monkeypatch.setitem(sys.modules, "torch", None)
    for name in [m for m in sys.modules if m == "learn.train" or m.startswith("learn.train.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setattr(sys, "argv", ["kiloforge-learn", "train", "--out", str(tmp_path / "run")])
    assert learn_script() == 2
    assert capsys.readouterr().err == "kiloforge-learn needs torch: pip install 'kiloforge[learn]'\n"
    assert list(tmp_path.iterdir()) == []


def test_learn_plot_without_learn_extra(tmp_path, monkeypatch):
    """`python -m learn plot` draws run curves, titled by their trainer, with torch, tyro and tensorboard unimportable."""
    for seed in (1, 2):
        run = tmp_path / f"es_s{seed}"
        run.mkdir()
        (run / "config.json").write_text(json.dumps({"algorithm": "es", "exp_name": "es", "n_robots": 4, "t_prev": 10}))
        (run / "metrics.csv").write_text("env_steps,eval_return,eval_final_coverage\n"
                                         f"100,{seed}.0,0.5\n200,{seed + 1}.0,0.{5 + seed}\n")
    r = kiloforge_run(["plot", "es_s1", "es_s2", "--out", "curves.png"], tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "wrote curves.png\n" and (tmp_path / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import learn.plots
    from learn.__main__ import build_parser, cmd_plot

    seen = {}  # the title names the runs' trainer
    monkeypatch.setattr(learn.plots, "plot_learning_curves", lambda groups, out, title, **kw: seen.setdefault("title", title))
    monkeypatch.chdir(tmp_path)
    cmd_plot(build_parser().parse_args(["plot", "es_s1", "--out", "t.png"]))
    assert seen["title"].startswith("ES learning curves")
    r = kiloforge_run(["plot", "missing_run"], tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "missing_run" in r.stderr


def test_learn_plot_averages_only_runs_that_differ_in_seed(tmp_path, monkeypatch):
    """Runs differing only in seed and budget share a curve; a run with another --reward gets its own, labelled."""
    import learn.plots
    from learn.__main__ import build_parser, cmd_plot

    cfgs = {"a1": {"seed": 1, "reward": "team"}, "a2": {"seed": 2, "reward": "team", "max_minutes": 9.0},
            "b1": {"seed": 1, "reward": "local"}}
    for name, extra in cfgs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(json.dumps({"algorithm": "magddpg", "exp_name": "x", "n_robots": 16,
                                                                 "t_prev": 1, **extra}))
        (tmp_path / name / "metrics.csv").write_text("env_steps,eval_return,eval_final_coverage\n100,1.0,0.5\n")
    seen = {}
    monkeypatch.setattr(learn.plots, "plot_learning_curves", lambda groups, out, title, **kw: seen.update(groups))
    monkeypatch.chdir(tmp_path)
    cmd_plot(build_parser().parse_args(["plot", "a1", "a2", "b1", "--out", "t.png"]))
    assert {k: len(v) for k, v in seen.items()} == {"x: 16 robots, T_prev 1, reward=team": 2,
                                                     "x: 16 robots, T_prev 1, reward=local": 1}


def test_export_onnx_without_learn_extra(tmp_path):
    """`python -m learn export-onnx` of the shipped .npz policy runs with torch, tyro and tensorboard unimportable."""
    pytest.importorskip("onnx")
    r = kiloforge_run(["export-onnx", "--policy", TINY_EVAL[1], "--out", "a.onnx"], tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "a.onnx").stat().st_size > 1000 and r.stdout.startswith("wrote a.onnx: ")


def test_learn_evaluate_labels_same_named_policies_apart(tmp_path):
    """Two policy files with the same name in different runs get two labels; the same file twice is one error line."""
    src = ROOT / "export" / "data" / "default_policy.npz"
    for run in ("r1", "r2"):
        (tmp_path / run / "generations").mkdir(parents=True)
        (tmp_path / run / "generations" / "gen_020.npz").write_bytes(src.read_bytes())
    a, b = (str(tmp_path / r / "generations" / "gen_020.npz") for r in ("r1", "r2"))
    rest = TINY_EVAL[2:]
    r = kiloforge_run(["evaluate", "--policy", a, b, *rest], tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 0, r.stderr
    names = set(json.loads((tmp_path / "ev" / "evaluation.json").read_text())["robots"]["4"]["metrics"])
    assert {"r1/generations/gen_020", "r2/generations/gen_020"} <= names
    r = kiloforge_run(["evaluate", "--policy", a, a, *rest[:-1], "ev2"], tmp_path, code=NO_LEARN_EXTRA)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "twice" in r.stderr
    assert not (tmp_path / "ev2").exists()


def test_learn_evaluate_takes_every_shipped_policy(tmp_path):
    """`learn evaluate` runs every shipped policy file, hand-written kinds included, and records each one's kind."""
    from kiloforge.shipped import load_task_policy, shipped_names
    from learn.evaluate import evaluate_policies

    pols = {name: load_task_policy(name) for name in shipped_names()}
    (tmp_path / "ev").mkdir()
    evaluate_policies(pols, [2], 1, 5, tmp_path / "ev", gif=False, progress=False, baselines=False)
    recorded = json.loads((tmp_path / "ev" / "evaluation.json").read_text())["policies"]
    assert {n: r["kind"] for n, r in recorded.items()} == {n: p.kind for n, p in pols.items()}
    assert "searcher" in {p.kind for p in pols.values()}
