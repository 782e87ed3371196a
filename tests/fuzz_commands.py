"""Fuzzing targets for issue 47: every command under hostile names, run folders, disks, standard outputs,
weights and the causes of part A, run in-process through the ``kiloforge`` command's whole entry machinery
(:func:`kiloforge.cli.main`: the stream handling of :mod:`kiloforge.stdio` included). Used by
tests/soak/fuzz_all.py (thousands of inputs) and tests/test_fuzz.py (a slice).

Each input ends in one of :data:`tests.fuzz_targets.OUTCOMES`. The property: exit 0 with every output
complete, or a refusal (exit 2; 1 for a check that failed; 141 when standard output's reader went away)
with exactly one line on stderr and the outputs as they were; never a traceback, never a hang
(:data:`HANG_S`), never a NumPy warning beside the one line, never a file the command was not given read.

Every environment is real: a FIFO, a link to ``/dev/zero``, ``/dev/full`` as standard output, a pipe whose
reader is closed, ``RLIMIT_FSIZE`` for a disk that fills (writes fail with ``EFBIG`` as with ``ENOSPC``), a
``CC`` that is not a compiler, an ONNX file pointing at a file beside it.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import resource
import shutil
import signal
import traceback
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import strategies as st

from kiloforge.policies import save_policy
from sim.config import preset
from tests.bad_inputs import crafted, parts, small_policy
from tests.fuzz_targets import _clean_message, base_policies, json_document, snapshot

HANG_S = 120  #: an input still running after this long is a hang
TEMPORARY = re.compile(r"\..*\.kf\d+-[0-9a-f]{8}\.(tmp|stage).*", re.S)  #: kiloforge.io's temporaries
SIM = ["--episodes", "1", "--steps", "3", "--quiet"]
EVAL = ["--robots", "2", "--episodes", "1", "--steps", "3", "--quiet", "--no-baselines"]
EXPORT = ["--robots-calib", "2", "--calib-steps", "3", "--quiet", "--no-avr"]
VERIFY = ["--episodes", "1", "--steps", "3", "--robots", "2", "--robots-calib", "2", "--calib-steps", "3", "--quiet"]
#: the files a command's success must leave (relative to its --out); "" : the --out file itself
OUTPUTS = {"sim": ("trajectories.png", "episode.gif", "coverage.png", "metrics.json"),
           "evaluate": ("evaluation.json",), "verify": ("coverage.png", "returns_box.png", "closed_loop.json"),
           "export": ("",), "rehash": ("",), "plot": ("",)}


class Hang(Exception):
    """An input ran past :data:`HANG_S`."""


def _alarm(signum: int, frame: Any) -> None:
    raise Hang(f"still running after {HANG_S} s")


def run_kiloforge(argv: list[str], stdout: Any = None) -> tuple[int | None, str, str, list[str]]:
    """``kiloforge ARGV`` in-process: (exit status or None, stderr, traceback or "hang: ...", warnings raised).
    ``stdout``: the stream it writes to (default a StringIO)."""
    from kiloforge.cli import main

    err = io.StringIO()
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(HANG_S)
    try:
        with warnings.catch_warnings(record=True) as seen, contextlib.redirect_stdout(stdout or io.StringIO()), \
                contextlib.redirect_stderr(err):
            warnings.simplefilter("always")
            try:
                rc = main(argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except Hang as e:
        return None, err.getvalue(), f"hang: {e}", []
    except BaseException:
        return None, err.getvalue(), traceback.format_exc(), []
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    return rc, err.getvalue(), "", [f"{w.category.__name__}: {w.message}" for w in seen]


def judge(argv: list[str], result: tuple, out_dir: Path, before: dict, expect: Callable[[], str] | None = None,
          ok_status: tuple[int, ...] = (0, 1, 2)) -> tuple[str, str]:
    """The outcome of one run: ``before`` is :func:`snapshot` of ``out_dir`` before it; ``expect()`` says what
    is missing from a successful run ('' when nothing is)."""
    rc, err, tb, warned = result
    detail = f"{argv!r} -> {rc}: {err[-600:]!r}"
    if tb:
        return ("hang" if tb.startswith("hang:") else "traceback"), f"{detail}\n{tb[-3000:]}"
    lines = [l for l in err.splitlines() if l.strip()]
    if rc not in ok_status:
        return "traceback", f"exit status {rc}: {detail}"
    if rc not in (0, 141):
        budget_verdict = rc == 1 and "budget" in argv and not lines
        if not budget_verdict and (len(lines) != 1 or not _clean_message(lines[0]) or warned):
            return "bad_message", f"{detail} warnings {warned}"
        after = snapshot(out_dir)
        if after != before:
            return "partial_output", f"changed {sorted(set(after.items()) ^ set(before.items()))[:6]} {detail}"
        return "rejected", ""
    if any("Traceback" in l for l in lines) or warned:
        return "bad_message", f"{detail} warnings {warned}"
    hidden = [k for k in snapshot(out_dir) if any(TEMPORARY.fullmatch(part) for part in Path(k).parts)]
    if hidden:
        return "partial_output", f"temporaries left: {hidden} {detail}"
    missing = expect() if expect is not None and rc == 0 else ""
    return ("partial_output", f"{missing} {detail}") if missing else ("accepted", "")


def _expect(command: str, out: Path) -> Callable[[], str]:
    def missing() -> str:
        names = OUTPUTS[command]
        gone = [n for n in names if not (out / n if n else out).is_file()]
        return f"missing {gone} in {out}" if gone else ""
    return missing


def fresh(d: Path) -> Path:
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    return d


# --- causes 3, 4, 5: names that reach plots, terminals and file systems --------------------------------
NAME_CHARS = "$\\{}^_%&#ab1 .-\udcff\udc80\u202e\x1b\x07\u00e9\u2713\u0663\U0001f600"


@st.composite
def hostile_name(draw) -> str:
    """A name of mathtext syntax, lone surrogates (a non-UTF-8 file name), control and bidi characters and
    other scripts; sometimes far longer than a file system allows."""
    text = draw(st.text(st.sampled_from(NAME_CHARS), min_size=1, max_size=24))
    if draw(st.integers(0, 3)) == 0:
        text = text + "x" * draw(st.integers(200, 320))
    return text.replace("/", "_")


class NameFixtures:
    """A valid policy and run folder to start from."""

    def __init__(self, root: Path) -> None:
        self.root = fresh(root)
        self.policy = save_policy(small_policy(), root / "p.npz")
        self.run = root / "run"
        self.run.mkdir()
        (self.run / "config.json").write_text('{"exp_name": "e", "n_robots": 2, "t_prev": 2, "algorithm": "es"}')
        (self.run / "metrics.csv").write_text("env_steps,eval_return,eval_final_coverage\n1,2,0.5\n2,3,0.6\n")


def _policy_named(work: Path, name: str, world_name: str | None) -> Path:
    """The fixture policy saved under ``name`` (bytes as the file system takes them), its world renamed (a
    name WorldConfig refuses is written into the file's meta, hashed, for the loader to refuse)."""
    path = work / (name + ".npz")
    arrays, meta = parts(small_policy())
    if world_name is not None:
        meta["world"] = {**meta["world"], "name": world_name}
    try:
        path.write_bytes(crafted(arrays, meta))
    except OSError:  # the name itself is what is tested: one the file system refuses is given as is
        pass
    return path


def names_case(data: Any, fx: NameFixtures, work: Path) -> tuple[str, str]:
    """A command with a hostile name as its output, its policy file's name, its world's name or a label."""
    command = data.draw(st.sampled_from(sorted(OUTPUTS)))
    where = data.draw(st.sampled_from(["out", "policy", "world", "label"]))
    name = data.draw(hostile_name())
    out_dir = fresh(work / "out")
    policy = str(fx.policy)
    if where in ("policy", "world") and command != "plot":
        policy = str(_policy_named(out_dir, name if where == "policy" else "w",
                                   name[:40] if where == "world" else None))
    run = fx.run
    if where == "label" and command == "plot":
        run = out_dir / "run"
        shutil.copytree(fx.run, run)
        (run / "config.json").write_text(json.dumps({"exp_name": name, "n_robots": 2}))
    target = out_dir / (name if where == "out" else "o")
    argv = {"sim": ["sim", "--policy", policy, "--out", str(target), *SIM],
            "evaluate": ["evaluate", "--policy", policy, "--out", str(target), *EVAL],
            "verify": ["verify", "--policy", policy, "--out", str(target), *VERIFY],
            "export": ["export", "--policy", policy, "--out", f"{target}.c", *EXPORT],
            "rehash": ["rehash", policy, "--out", f"{target}.npz"],
            "plot": ["plot", str(run), "--out", f"{target}.png"] + (["--title", name] if where == "label" else [])
            }[command]
    out_file = Path(argv[argv.index("--out") + 1])
    before = snapshot(out_dir)
    return judge(argv, run_kiloforge(argv), out_dir, before, _expect(command, out_file))


# --- cause 8: run folders --------------------------------------------------------------------------
CSV_HEADER = ["env_steps", "eval_return", "eval_final_coverage", "train_return"]


@st.composite
def metrics_text(draw) -> bytes:
    """A metrics.csv: valid rows, then a column dropped or renamed, a row longer or shorter than the header,
    a field of thousands of characters, text or NaN for a number, bytes that are not UTF-8, quoted newlines."""
    header = list(CSV_HEADER)
    rows = [[str(draw(st.integers(0, 10**6))), repr(draw(st.floats(-10, 10))), "0.5", "1"]
            for _ in range(draw(st.integers(0, 5)))]
    op = draw(st.sampled_from(["drop_column", "rename", "long_row", "short_row", "long_field", "text", "nan",
                               "not_utf8", "quoted_newlines", "empty", "bom", "dup_column", "valid"]))
    if op == "drop_column":
        k = draw(st.integers(0, 2))
        header.pop(k)
        rows = [r[:k] + r[k + 1:] for r in rows]
    elif op == "rename":
        header[draw(st.integers(0, 2))] = draw(st.sampled_from(["Env_steps", "eval return", "", "x"]))
    elif op == "long_row" and rows:
        rows[-1] += ["9"] * draw(st.integers(1, 3))
    elif op == "short_row" and rows:
        rows[-1] = rows[-1][:draw(st.integers(0, 3))]
    elif op == "long_field" and rows:
        rows[-1][draw(st.integers(0, 3))] = "1" * draw(st.integers(65, 300_000))
    elif op == "text" and rows:
        rows[-1][draw(st.integers(0, 3))] = draw(st.sampled_from(["x", "1e999x", "--", "0x10", "\x1b[2J"]))
    elif op == "nan" and rows:
        rows[-1][draw(st.integers(0, 3))] = draw(st.sampled_from(["nan", "inf", "-inf", ""]))
    elif op == "dup_column":
        header[3] = "eval_return"
    text = "\n".join(",".join(r) for r in [header] + rows) + "\n"
    if op == "quoted_newlines":
        text += '1,"' + "2\n" * draw(st.integers(1, 80_000)) + '",0.5,1\n'
    raw = text.encode()
    if op == "not_utf8":
        raw += b"3,\xff\xfe,0.5,1\n"
    elif op == "empty":
        raw = b""
    elif op == "bom":
        raw = b"\xef\xbb\xbf" + raw
    return raw


CONFIG_BASE = {"exp_name": "run", "n_robots": [4, 16], "t_prev": 2, "algorithm": "magddpg", "seed": 1}


def run_folder_case(data: Any, work: Path) -> tuple[str, str]:
    """learn plot of a run folder whose config.json or metrics.csv is mutated, or is not a regular file."""
    out_dir = fresh(work / "out")
    run = out_dir / "run"
    run.mkdir()
    config = data.draw(st.one_of(json_document(CONFIG_BASE), st.sampled_from(["[1, 2]", "3", '"x"', "null", ""])))
    (run / "config.json").write_text(config, encoding="utf-8", errors="surrogatepass")
    (run / "metrics.csv").write_bytes(data.draw(metrics_text()))
    kind = data.draw(st.sampled_from(["file"] * 6 + ["fifo", "dev_zero", "directory", "missing"]))
    if kind != "file":
        victim = run / data.draw(st.sampled_from(["config.json", "metrics.csv"]))
        victim.unlink()
        if kind == "fifo":
            os.mkfifo(victim)
        elif kind == "dev_zero":
            os.symlink("/dev/zero", victim)
        elif kind == "directory":
            victim.mkdir()
    argv = ["plot", str(run), "--out", str(out_dir / "c.png")]
    before = snapshot(out_dir)
    return judge(argv, run_kiloforge(argv), out_dir, before, _expect("plot", out_dir / "c.png"))


# --- cause 7: standard output that fails ------------------------------------------------------------
def stdout_case(data: Any, fx: NameFixtures, work: Path) -> tuple[str, str]:
    """A command printing to /dev/full, to a pipe whose reader is gone, or to an ASCII-only stream while it
    prints a world name in other scripts."""
    out_dir = fresh(work / "out")
    mode = data.draw(st.sampled_from(["full", "closed_pipe", "ascii"]))
    unicode_policy = _policy_named(out_dir, "u", "kil\u00f6bot\u2713\u0663") if mode == "ascii" else fx.policy
    command = data.draw(st.sampled_from([["--version"], ["budget", "--hidden", "4", "--history", "2"],
                                         ["budget", "--gru", str(data.draw(st.integers(1, 200)))], ["sim", "--help"],
                                         ["export", "--policy", str(unicode_policy), "--out", str(out_dir / "k.c"),
                                          *EXPORT], ["learn", "--version"], ["rehash", "--help"],
                                         ["sim", "--policy", str(unicode_policy), "--out", str(out_dir / "s"), *SIM]]))
    line_buffering = data.draw(st.booleans())
    if mode == "full":
        raw = open("/dev/full", "wb", buffering=0)
    elif mode == "closed_pipe":
        r, w = os.pipe()
        os.close(r)
        raw = open(w, "wb", buffering=0)
    else:
        raw = open(os.devnull, "wb", buffering=0)
    stream = io.TextIOWrapper(io.BufferedWriter(raw), encoding="ascii" if mode == "ascii" else "utf-8",
                              errors="strict", line_buffering=line_buffering)
    before = snapshot(out_dir)
    try:
        result = run_kiloforge(list(command), stdout=stream)
    finally:
        with contextlib.suppress(OSError):
            stream.close()
    rc, err, tb, warned = result
    if not tb and mode == "closed_pipe" and rc == 141 and err:
        return "bad_message", f"{command!r}: a closed pipe printed {err!r}"
    if not tb and mode == "full" and rc == 0:
        return "bad_message", f"{command!r}: exit 0 although standard output failed"
    if not tb and rc == 2 and ("the command itself completed" in err or "written completely" in err):
        # its files are complete sets: judged as a success (a closed set, no temporaries)
        return judge(list(command), (0, "", "", result[3]), out_dir, before, None)
    return judge(list(command), result, out_dir, before, None, ok_status=(0, 1, 2, 141))


# --- cause 6: a disk that fills ---------------------------------------------------------------------
def disk_full_case(data: Any, fx: NameFixtures, work: Path) -> tuple[str, str]:
    """A command writing its files while at most a few KiB may be written (RLIMIT_FSIZE)."""
    command = data.draw(st.sampled_from(sorted(OUTPUTS)))
    out_dir = fresh(work / "out")
    target = out_dir / "o"
    argv = {"sim": ["sim", "--out", str(target), *SIM],
            "evaluate": ["evaluate", "--policy", str(fx.policy), "--out", str(target), *EVAL],
            "verify": ["verify", "--policy", str(fx.policy), "--out", str(target), *VERIFY],
            "export": ["export", "--policy", str(fx.policy), "--out", f"{target}.c", *EXPORT],
            "rehash": ["rehash", str(fx.policy), "--out", f"{target}.npz"],
            "plot": ["plot", str(fx.run), "--out", f"{target}.png"]}[command]
    limit = data.draw(st.integers(0, 64)) * 1024
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    before = snapshot(out_dir)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        result = run_kiloforge(argv)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    return judge(argv, result, out_dir, before, _expect(command, Path(argv[argv.index("--out") + 1])))


# --- cause 11: weights beyond the int8 format --------------------------------------------------------
def weights_case(data: Any, work: Path) -> tuple[str, str]:
    """An MLP, GRU or LSTM policy with one array scaled by 10^4 .. 10^38 (re-hashed: loading accepts it),
    exported or simulated."""
    pol = base_policies()[data.draw(st.sampled_from(["mlp", "gru", "lstm"]))]
    arrays, meta = parts(pol)
    name = data.draw(st.sampled_from(sorted(arrays)))
    scale = 10.0 ** data.draw(st.floats(4, 38)) * data.draw(st.sampled_from([1, -1]))
    a = arrays[name].astype(np.float64)
    if data.draw(st.booleans()):
        a = a * scale
    else:
        a.flat[data.draw(st.integers(0, a.size - 1))] = scale
    arrays[name] = np.clip(a, -3e38, 3e38).astype(np.float32)
    out_dir = fresh(work / "out")
    path = out_dir / "w.npz"
    path.write_bytes(crafted(arrays, meta))
    command = data.draw(st.sampled_from(["export", "export", "sim"]))
    argv = (["export", "--policy", str(path), "--out", str(out_dir / "k.c"), *EXPORT] if command == "export"
            else ["sim", "--policy", str(path), "--out", str(out_dir / "s"), *SIM])
    before = snapshot(out_dir)
    out = Path(argv[argv.index("--out") + 1])
    return judge(argv, run_kiloforge(argv), out_dir, before, _expect(command, out))


# --- part A's causes: searcher parameters, world constants, long episodes, CC, target uids, ONNX --------
def _searcher_file(path: Path, name: str, value: Any) -> Path:
    from kiloforge.actors.searcher import searcher_policy

    meta = searcher_policy(preset("kilobot")).meta()
    meta["params"] = {**meta["params"], name: value}
    path.write_bytes(crafted({}, meta))
    return path


def part_a_case(data: Any, fx: NameFixtures, work: Path) -> tuple[str, str]:
    """One of part A's causes with a generated value; the ONNX case with ``secret.bin`` beside the model."""
    from sim.baselines import PARAM_RANGES

    out_dir = fresh(work / "out")
    cause = data.draw(st.sampled_from(["searcher", "world", "long", "cc", "uids", "onnx"]))
    env: dict[str, str] = {}
    if cause == "searcher":
        name = data.draw(st.sampled_from(sorted(PARAM_RANGES)))
        lo, hi = PARAM_RANGES[name]
        value = data.draw(st.one_of(st.integers(-10**9, 10**30), st.floats(-1e308, 1e308, allow_nan=False),
                                    st.sampled_from([lo, hi, True, None, "1"])))
        policy = _searcher_file(out_dir / "s.npz", name, value)
        command = data.draw(st.sampled_from(["export", "sim"]))
        argv = (["export", "--policy", str(policy), "--out", str(out_dir / "k.c"), *EXPORT] if command == "export"
                else ["sim", "--policy", str(policy), "--out", str(out_dir / "o"), *SIM])
    elif cause in ("world", "long"):
        arrays, meta = parts(small_policy())
        if cause == "world":
            key = data.draw(st.sampled_from(["rbf_sigma_mm", "rbf_norm", "rbf_lo_mm", "rbf_hi_mm"]))
            change = {key: float(10.0 ** data.draw(st.floats(-300, 300)))}
        else:
            change = {"episode_steps": data.draw(st.integers(10_001, 10**9))}
        meta["world"] = {**meta["world"], **change}
        policy = out_dir / "p.npz"
        policy.write_bytes(crafted(arrays, meta))
        command = data.draw(st.sampled_from(["export", "sim", "verify"]))
        fast = [a for a in EXPORT if cause != "long" or a not in ("--calib-steps", "3")]
        argv = {"export": ["export", "--policy", str(policy), "--out", str(out_dir / "k.c"), *fast],
                "sim": ["sim", "--policy", str(policy), "--out", str(out_dir / "o"), "--episodes", "1", "--quiet"]
                + ([] if cause == "long" else ["--steps", "3"]),
                "verify": ["verify", "--policy", str(policy), *VERIFY]}[command]
    elif cause == "cc":
        env["CC"] = data.draw(st.sampled_from(["/bin/true", "false", "gcc -O2 -x", 'gcc "-O2', "echo -n",
                                               str(out_dir), str(out_dir / "none"), "/dev/null", ""]))
        argv = ["export", "--out", str(out_dir / "k.c"), "--verify", "host", *EXPORT]
    elif cause == "uids":
        uids = data.draw(st.text(st.sampled_from("0123456789,_+-\u0663\u00b2\uff11 x"), min_size=1, max_size=12))
        argv = ["export", "--out", str(out_dir / "k.c"), "--target-uids", uids, *EXPORT]
    else:
        model, secret = _onnx_pointing_at_secret(out_dir, data)
        argv = ["export", "--onnx", str(model), "--world-json", str(_world_json(out_dir)),
                "--out", str(out_dir / "k.c"), *EXPORT]
    before = snapshot(out_dir)
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        result = run_kiloforge(argv)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    if cause == "onnx" and result[0] == 0:
        return "accepted_corrupt", f"an ONNX model with external data was exported: {argv!r}"
    command = argv[0]
    out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else out_dir
    return judge(argv, result, out_dir, before, _expect(command, out) if "--out" in argv else None)


def _world_json(d: Path) -> Path:
    p = d / "w.json"
    p.write_text('{"world": "thesis", "t_prev": 1}')
    return p


def _onnx_pointing_at_secret(d: Path, data: Any) -> tuple[Path, Path]:
    """The tiny ONNX actor with one weight moved to external data (in an initializer, or a Constant node)
    that names ``secret.bin``, which exists beside it with plausible weights."""
    from onnx import TensorProto, helper, load

    from tests.onnx_models import tiny_model

    m = load(str(tiny_model(d / "base.onnx", metadata=False)))
    g = m.graph
    t = g.initializer[data.draw(st.integers(0, len(g.initializer) - 1))]
    secret = d / "secret.bin"
    secret.write_bytes(np.ones(int(np.prod(t.dims)), np.float32).tobytes())
    moved = type(t)()
    moved.CopyFrom(t)
    moved.ClearField("raw_data")
    moved.ClearField("float_data")
    moved.data_location = TensorProto.EXTERNAL
    moved.external_data.add(key="location", value=data.draw(st.sampled_from(["secret.bin", "./secret.bin",
                                                                             str(secret)])))
    if data.draw(st.booleans()):
        g.initializer.remove(t)
        g.node.insert(0, helper.make_node("Constant", [], [moved.name], value=moved))
    else:
        t.CopyFrom(moved)
    path = d / "m.onnx"
    path.write_bytes(m.SerializeToString())
    return path, secret
