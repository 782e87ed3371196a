"""One set of flag names across every command line (sim, learn, export): names, meanings, --version, strictness."""
from __future__ import annotations

import argparse

import pytest

import kiloforge
from export.cli.budget import budget_parser
from export.cli.firmware import export_parser
from export.cli.rehash import rehash_parser
from export.cli.verify import verify_parser
from kiloforge.cliparse import version_line
from kiloforge.sim_cli import build_parser as sim_parser
from sim.config import MAX_ROBOTS



def learn_parsers() -> dict[str, argparse.ArgumentParser]:
    """The argparse parsers of ``python -m learn`` (top level, evaluate, plot), built without torch."""
    from learn.__main__ import build_parser

    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    return {"learn": top, "learn evaluate": sub.choices["evaluate"], "learn plot": sub.choices["plot"]}


def parsers() -> dict[str, argparse.ArgumentParser]:
    """Every argparse parser of the project's entry points, by command."""
    return {"sim": sim_parser(), "export": export_parser(), "export verify": verify_parser(),
            "export budget": budget_parser(), "export rehash": rehash_parser(), **learn_parsers()}


def visible(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The options ``--help`` shows (deprecated aliases are hidden), by option string."""
    return {s: a for a in p._actions if a.help != argparse.SUPPRESS for s in a.option_strings}


#: commands that print progress bars, so have --quiet
PROGRESS = ("sim", "export", "export verify", "learn evaluate")
#: commands that run several swarm sizes: --robots takes a list
SIZES = ("sim", "export verify", "learn evaluate")


@pytest.mark.parametrize("name", list(parsers()))
def test_no_old_flag_names(name):
    """No command shows --envs, --no-progress, or --preset meaning a world; --world is the world preset."""
    opts = visible(parsers()[name])
    assert "--envs" not in opts and "--no-progress" not in opts and "--preset" not in opts
    if "--world" in opts:
        assert "world preset" in opts["--world"].help


@pytest.mark.parametrize("name", list(parsers()))
def test_every_parser_has_version_and_refuses_abbreviations(name):
    """Every parser has --version and allow_abbrev off."""
    p = parsers()[name]
    assert "--version" in visible(p) and p.allow_abbrev is False


@pytest.mark.parametrize("name", PROGRESS)
def test_quiet_where_progress_is_printed(name):
    """Every command with a progress bar has --quiet (a flag without a value)."""
    assert visible(parsers()[name])["--quiet"].nargs == 0


@pytest.mark.parametrize("name", SIZES)
def test_robots_is_a_list_up_to_max_robots(name):
    """--robots takes one or more counts, each in 1..MAX_ROBOTS, in every command that runs swarm sizes."""
    p = parsers()[name]
    assert visible(p)["--robots"].nargs == "+"
    required = {"sim": ["--out", "o"], "learn evaluate": ["--policy", "p.npz", "--out", "o"]}.get(name, [])
    a = p.parse_args([*required, "--robots", "2", str(MAX_ROBOTS)])
    assert a.robots == [2, MAX_ROBOTS]
    with pytest.raises((SystemExit, Exception)):
        p.parse_args([*required, "--robots", str(MAX_ROBOTS + 1)])


def test_n_envs_is_one_name():
    """The environments simulated together are --n-envs in sim and learn evaluate."""
    for name in ("sim", "learn evaluate"):
        assert "--n-envs" in visible(parsers()[name])


def entry_point(command: str):
    """The ``main(argv)`` of a command: ``sim``, ``export`` or ``learn``."""
    from export.__main__ import main as export_main
    from learn.__main__ import main as learn_main
    from sim.__main__ import main as sim_main

    return {"sim": sim_main, "export": export_main, "learn": learn_main}[command]


def call(argv: list[str]) -> int:
    """Run ``python -m ARGV[0] ARGV[1:]`` in this process; its exit status (SystemExit included)."""
    try:
        return entry_point(argv[0])(argv[1:])
    except SystemExit as e:
        return int(e.code or 0)


@pytest.mark.parametrize("argv,old,new", [
    (["sim", "--preset", "kilobot", "--envs", "1", "--episodes", "1", "--steps", "3", "--quiet"],
     ["--preset", "--envs"], ["--world", "--n-envs"]),
    (["export", "budget", "--preset", "kilobot", "--history", "3", "--hidden", "8"], ["--preset"], ["--world"]),
])
def test_deprecated_spellings_still_work_with_a_note(argv, old, new, tmp_path, capsys):
    """An old flag name still works (documented commands keep running) and prints one deprecation note each."""
    if argv[0] == "sim":
        argv = [*argv, "--out", str(tmp_path / "o")]
    assert call(argv) == 0
    notes = [ln.split(": note: ")[1] for ln in capsys.readouterr().err.splitlines() if ": note: " in ln]
    assert notes == [f"{o} is deprecated, use {n}" for o, n in zip(old, new)]


@pytest.mark.parametrize("argv", [["sim"], ["export"], ["export", "verify"], ["export", "budget"], ["learn"],
                                  ["learn", "evaluate"], ["learn", "train"], ["learn", "train-es"]])
def test_version_on_every_entry_point(argv, capsys):
    """`python -m <entry point> [sub-command] --version` prints the one version line, exit 0."""
    assert call([*argv, "--version"]) == 0
    assert capsys.readouterr().out.strip() == version_line() == f"kiloforge {kiloforge.__version__}"


@pytest.mark.parametrize("argv,prog", [
    (["sim", "--out", "o", "--rob", "4"], "python -m sim"),
    (["export", "--polic", "x.npz"], "python -m export"),
    (["export", "verify", "--episode", "1"], "python -m export verify"),
    (["export", "budget", "--hist", "3"], "python -m export budget"),
    (["learn", "evaluate", "--policy", "p.npz", "--out", "o", "--step", "3"], "python -m learn evaluate"),
])
def test_abbreviation_refused_with_one_error_line(argv, prog, tmp_path, monkeypatch, capsys):
    """An abbreviated option is refused: exit 2, one line '<prog>: error: ...' naming it, nothing written."""
    monkeypatch.chdir(tmp_path)
    assert call(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: ") and argv[-2] in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_closed_loop_flag_is_a_deprecated_no_op(capsys):
    """`export verify --closed-loop` (its only mode) is accepted with one note on stderr, hidden from --help,
    and changes nothing that is parsed."""
    p = verify_parser()
    assert vars(p.parse_args(["--closed-loop"])) == vars(p.parse_args([]))
    note = capsys.readouterr().err.strip().splitlines()
    assert note == ["python -m export verify: note: --closed-loop does nothing (the closed-loop comparison is the only "
                    "thing verify does) and will be removed; leave it out"]
    assert "--closed-loop" not in visible(p)


LEARN = ["learn", "evaluate", "--policy", "p.npz"]


@pytest.mark.parametrize("argv,prog,line", [
    (["sim", "--robot", "8"], "python -m sim", "unrecognized option --robot; did you mean --robots?"),
    (["sim", "--out", "o", "--stepz=3"], "python -m sim", "unrecognized option --stepz; did you mean --steps?"),
    (["export", "--polcy", "x.npz"], "python -m export", "unrecognized option --polcy; did you mean --policy?"),
    (["export", "verify", "--robot", "8"], "python -m export verify", "unrecognized option --robot; did you mean --robots?"),
    (["export", "budget", "--hiden", "8"], "python -m export budget", "unrecognized option --hiden; did you mean --hidden?"),
    ([*LEARN, "--robot", "8"], "python -m learn evaluate", "unrecognized option --robot; did you mean --robots?"),
    (["learn", "plot", "r", "--titel", "t"], "python -m learn plot", "unrecognized option --titel; did you mean --title?"),
    (["learn", "train", "--robot", "8"], "python -m learn train", "unrecognized option --robot; did you mean --robots?"),
    (["learn", "train-recurrent", "--cel", "gru"], "python -m learn train-recurrent",
     "unrecognized option --cel; did you mean --cell?"),
    (["learn", "train-es", "--robot", "8"], "python -m learn train-es", "unrecognized option --robot; did you mean --robots?"),
    (["learn", "train-es", "--xyzzy"], "python -m learn train-es", "unrecognized option --xyzzy (--help lists the options)"),
])
def test_misspelled_option_names_the_closest(argv, prog, line, tmp_path, monkeypatch, capsys):
    """A misspelled option is answered in one line with the closest valid one, exit 2, nothing written."""
    if "train" in argv[1]:
        pytest.importorskip("torch")
    monkeypatch.chdir(tmp_path)
    assert call(argv) == 2
    assert capsys.readouterr().err == f"{prog}: error: {line}\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command,shown", [
    ("train", ["--preset {default,thesis,fast,quick,guided}", "--world {kilobot,thesis}", "--version"]),
    ("train-recurrent", ["--preset {fast,quick,guided}", "--cell {gru,lstm}", "--version"]),
    ("train-es", ["--preset {default,quick}", "--randomise {none,", "--demo-policy {none,searcher,pusher}", "--version"]),
])
def test_trainer_help_lists_choices_and_version(command, shown, capsys, monkeypatch):
    """A trainer's --help lists the choices of --preset and of the other named values, and --version."""
    pytest.importorskip("torch")
    monkeypatch.setenv("COLUMNS", "200")
    assert call(["learn", command, "--help"]) == 0
    out = capsys.readouterr().out
    assert "{None}" not in out and all(s in out for s in shown), out


def test_export_policy_help_names_every_shipped_policy():
    """`--policy` of export and verify names every shipped policy (default, searcher, pusher)."""
    from export.cli.common import SHIPPED_POLICIES

    names = [n for shipped in SHIPPED_POLICIES.values() for n in shipped]
    assert set(names) >= {"default", "searcher", "pusher"}
    for name in ("export", "export verify"):
        assert all(n in visible(parsers()[name])["--policy"].help for n in names)


def test_kiloforge_learn_help_names_itself(capsys):
    """`kiloforge learn --help` shows learn's own help, pointing to `kiloforge learn <command> --help`."""
    from kiloforge.cli import main as kiloforge_main

    try:
        kiloforge_main(["learn", "--help"])
    except SystemExit as e:
        assert e.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: kiloforge learn") and "kiloforge learn train-es --help" in " ".join(out.split())
    assert "python -m learn" not in out


def test_steps_defaults_say_why_they_differ():
    """sim runs the world's episode, learn evaluate the thesis benchmark's 500 steps; both helps say so."""
    sim_help = visible(parsers()["sim"])["--steps"].help
    eval_steps = visible(parsers()["learn evaluate"])["--steps"]
    assert eval_steps.default == 500 and "benchmark" in eval_steps.help and "python -m sim" in eval_steps.help
    assert parsers()["sim"].parse_args(["--out", "o"]).steps is None and "benchmark" in sim_help


def test_mixed_worlds_are_named(tmp_path):
    """Evaluating policies of different worlds names each policy with its world (item 9), before any output."""
    from tests.fixtures import init_policy
    from learn.evaluate import evaluate_policies
    from sim.config import preset

    pols = {"a": init_policy(preset("thesis"), 2, (4,), "elu", seed=1),
            "b": init_policy(preset("kilobot"), 2, (4,), "elu", seed=2)}
    with pytest.raises(ValueError) as e:
        evaluate_policies(pols, [2], 1, 3, tmp_path / "out", gif=False, progress=False)
    assert "a ('thesis')" in str(e.value) and "b ('kilobot')" in str(e.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, line", [
    (["train-es", "--robots", "0"], "python -m learn train-es: error: --robots must be in 1..1024, got 0"),
    (["train", "--history", "0"], "python -m learn train: error: --history must be in 1..200, got 0"),
    (["train-es", "--max-minutes", "-1"], "python -m learn train-es: error: --max-minutes must be >= 0, got -1.0"),
])
def test_training_errors_name_the_flag(argv, line, tmp_path, monkeypatch, capsys):
    """A bad value given to a trainer's flag is refused in one line that names the flag, not the config field."""
    pytest.importorskip("torch")
    from learn.__main__ import main as learn_main

    monkeypatch.chdir(tmp_path)
    assert learn_main([*argv, "--out", "run"]) == 2
    assert capsys.readouterr().err == line + "\n"
    assert list(tmp_path.iterdir()) == []


def test_kilobot_world_is_every_commands_default(tmp_path):
    """Without --world, sim and every trainer (train, train-recurrent, train-es) run the kilobot world; the thesis
    world only on request."""
    import json

    from sim.config import DEFAULT_WORLD

    assert DEFAULT_WORLD == "kilobot"
    assert call(["sim", "--out", str(tmp_path / "o"), "--robots", "2", "--episodes", "1", "--steps", "3", "--quiet"]) == 0
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["world"]["name"] == "kilobot"
    pytest.importorskip("tyro")
    from learn.cli import parse_train_args
    from learn.config import ESConfig, RecurrentConfig, TrainConfig

    for cls, preset in ((TrainConfig, "default"), (RecurrentConfig, "fast"), (ESConfig, "default")):
        assert parse_train_args(["--out", "r"], cls, "p", preset)[0].world == "kilobot"
        assert parse_train_args(["--out", "r", "--world", "thesis"], cls, "p", preset)[0].world == "thesis"
