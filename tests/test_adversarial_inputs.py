"""Adversarial inputs of issue 47 (part A): generated variants of each cause, every one ending in one
clean line with exit 2 (or working as documented), never a traceback, never a file it was not given."""
from __future__ import annotations

import numpy as np
import pytest

from tests.bad_inputs import assert_one_clean_line
from export.cli.main import main as export_main
from tests.onnx_models import tiny_model

FAST = ["--robots-calib", "2", "--calib-steps", "4", "--quiet", "--no-avr"]


def _export_refused(argv, capsys) -> str:
    rc = export_main(argv)
    out, err = capsys.readouterr()
    assert rc == 2, (out, err)
    return assert_one_clean_line(err)


# --- ONNX: tensors anywhere in the model ------------------------------------------------------------
def _base(tmp_path):
    onnx = pytest.importorskip("onnx")
    return onnx.load(str(tiny_model(tmp_path / "base.onnx")))


def _external(t, location: str = "secret.bin") -> None:
    from onnx import TensorProto
    t.ClearField("raw_data")
    t.ClearField("float_data")
    t.data_location = TensorProto.EXTERNAL
    t.external_data.add(key="location", value=location)


def _weight_as_constant(m, location="secret.bin"):
    """w1 moves from the initializers into a Constant node whose value is external."""
    from onnx import helper
    g = m.graph
    w1 = next(t for t in g.initializer if t.name == "w1")
    t = type(w1)()
    t.CopyFrom(w1)
    g.initializer.remove(w1)
    _external(t, location)
    g.node.insert(0, helper.make_node("Constant", [], ["w1"], value=t))


def _constant_in_subgraph(m, location="secret.bin"):
    """An If node whose branches hold a Constant with external data."""
    from onnx import TensorProto, helper, numpy_helper
    t = numpy_helper.from_array(np.zeros(2, np.float32), "c")
    _external(t, location)
    branch = helper.make_graph([helper.make_node("Constant", [], ["o"], value=t)], "b", [],
                               [helper.make_tensor_value_info("o", TensorProto.FLOAT, [2])])
    m.graph.initializer.append(numpy_helper.from_array(np.array(True), "cond"))
    m.graph.node.append(helper.make_node("If", ["cond"], ["unused"], then_branch=branch, else_branch=branch))


def _attribute_tensor(m, location="secret.bin"):
    """A tensor attribute (not Constant's) on an ordinary node."""
    from onnx import helper, numpy_helper
    t = numpy_helper.from_array(np.zeros(4, np.float32), "aux")
    _external(t, location)
    m.graph.node[1].attribute.append(helper.make_attribute("aux", t))


def _nested_initializer(m, location="secret.bin"):
    """An initializer of a Loop body subgraph stored externally."""
    from onnx import TensorProto, helper, numpy_helper
    t = numpy_helper.from_array(np.zeros(3, np.float32), "inner")
    _external(t, location)
    body = helper.make_graph([helper.make_node("Identity", ["inner"], ["o"])], "body", [],
                             [helper.make_tensor_value_info("o", TensorProto.FLOAT, [3])], initializer=[t])
    m.graph.node.append(helper.make_node("Loop", ["", ""], ["z"], body=body))


def _function_body(m, location="secret.bin"):
    """A model-local function whose Constant is external."""
    from onnx import helper, numpy_helper
    t = numpy_helper.from_array(np.zeros(2, np.float32), "f")
    _external(t, location)
    f = helper.make_function("local", "f1", [], ["o"], [helper.make_node("Constant", [], ["o"], value=t)],
                             [helper.make_opsetid("", 17)])
    m.functions.append(f)


def _sparse_initializer(m, location=None):
    from onnx import helper, numpy_helper
    vals = numpy_helper.from_array(np.ones(2, np.float32), "sp")
    idx = numpy_helper.from_array(np.array([0, 3], np.int64), "")
    m.graph.sparse_initializer.append(helper.make_sparse_tensor(vals, idx, [8]))


def _sparse_constant(m, location=None):
    from onnx import helper, numpy_helper
    vals = numpy_helper.from_array(np.ones(2, np.float32), "spc")
    idx = numpy_helper.from_array(np.array([1, 2], np.int64), "")
    sp = helper.make_sparse_tensor(vals, idx, [4])
    m.graph.node.insert(0, helper.make_node("Constant", [], ["spc_out"], sparse_value=sp))


EXTERNAL = {"constant value": _weight_as_constant, "If branch constant": _constant_in_subgraph,
            "node attribute": _attribute_tensor, "Loop body initializer": _nested_initializer,
            "function constant": _function_body}


@pytest.mark.parametrize("location", ["secret.bin", "./secret.bin", "sub/../secret.bin"])
@pytest.mark.parametrize("where", sorted(EXTERNAL))
def test_onnx_external_data_anywhere_is_never_read(tmp_path, monkeypatch, capsys, where, location):
    """External data in a Constant, a subgraph, an attribute or a function: refused by name, the file beside it never becomes weights."""
    m = _base(tmp_path)
    EXTERNAL[where](m, location)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "secret.bin").write_bytes(np.full(1 << 16, 0.25, np.float32).tobytes())
    import onnx.external_data_helper as edh

    def never(*a, **k):
        raise AssertionError("external data was read")
    monkeypatch.setattr(edh, "load_external_data_for_tensor", never)
    p = tmp_path / "m.onnx"
    p.write_bytes(m.SerializeToString())
    msg = _export_refused(["--onnx", str(p), "--out", str(tmp_path / "k.c"), *FAST], capsys)
    assert "external data file" in msg and "never read" in msg
    assert not (tmp_path / "k.c").exists()


@pytest.mark.parametrize("how", [_sparse_initializer, _sparse_constant])
def test_onnx_sparse_tensors_are_refused(tmp_path, capsys, how):
    """A sparse initializer or a Constant sparse_value: one line naming the sparse tensor."""
    m = _base(tmp_path)
    how(m)
    p = tmp_path / "m.onnx"
    p.write_bytes(m.SerializeToString())
    assert "sparse tensor" in _export_refused(["--onnx", str(p), "--out", str(tmp_path / "k.c"), *FAST], capsys)


def _string_tensor(name):
    from onnx import TensorProto, helper
    return helper.make_tensor(name, TensorProto.STRING, [2], [b"a", b"b"])


def _typed_tensor(name, dtype):
    from onnx import helper
    t = helper.make_tensor(name, 1, [2], [0.5, 0.5])
    t.data_type = dtype
    return t


@pytest.mark.parametrize("dtype", ["STRING", "COMPLEX64", "COMPLEX128", "BFLOAT16", "FLOAT8E4M3FN", "INT4",
                                   "UNDEFINED", 999])
@pytest.mark.parametrize("place", ["initializer", "constant"])
def test_onnx_non_numeric_tensors_are_refused(tmp_path, capsys, dtype, place):
    """String, complex, bfloat16, float8, int4, undefined or unknown element types: one line naming the type."""
    from onnx import TensorProto, helper, numpy_helper
    m = _base(tmp_path)
    code = dtype if isinstance(dtype, int) else getattr(TensorProto, dtype)
    if dtype == "STRING":
        t = _string_tensor("b2")
    elif str(dtype).startswith("COMPLEX"):
        t = numpy_helper.from_array(np.array([0.5 + 1j, 0.5], np.complex64 if dtype == "COMPLEX64" else np.complex128), "b2")
    else:
        t = _typed_tensor("b2", code)
    g = m.graph
    g.initializer.remove(next(x for x in g.initializer if x.name == "b2"))
    if place == "initializer":
        g.initializer.append(t)
    else:
        g.node.insert(0, helper.make_node("Constant", [], ["b2"], value=t))
    p = tmp_path / "m.onnx"
    p.write_bytes(m.SerializeToString())
    msg = _export_refused(["--onnx", str(p), "--out", str(tmp_path / "k.c"), *FAST], capsys)
    assert "element type" in msg


# --- searcher parameters: bounded by explicit checks (item 9) ---------------------------------------
def _searcher_parts():
    from kiloforge.actors.searcher import searcher_policy
    from sim.config import preset
    return {}, searcher_policy(preset("kilobot")).meta()


def _bad_params(rng: np.random.Generator) -> list[tuple[str, object]]:
    """Generated out-of-range values for each bounded field: beyond the byte / uint16 limit, negative, huge, non-finite."""
    from sim.baselines import PARAM_RANGES
    out = []
    for name, (lo, hi) in sorted(PARAM_RANGES.items()):
        is_int = isinstance(hi, int)
        big = int(hi) + 1 + int(rng.integers(0, 10 ** 6)) if is_int else float(hi) * (1 + rng.random() * 1e6) + 1e-3
        out += [(name, big), (name, -1 - int(rng.integers(0, 1000)) if is_int else -rng.random() - 1e-9)]
        out += [(name, 10 ** 30)] if is_int else [(name, -1e308), (name, 1e308)]  # files hold no NaN / inf (strict JSON)
    return out + [("speed", 0.0), ("turn_sign", 3), ("uturn_steps", True), ("run_max_steps", 300.5)]


BAD_PARAMS = _bad_params(np.random.default_rng(np.random.SeedSequence(4711)))


@pytest.mark.parametrize("name,value", BAD_PARAMS, ids=[f"{n}={v!r}" for n, v in BAD_PARAMS])
def test_searcher_parameter_out_of_range_is_one_line(tmp_path, capsys, name, value):
    """A searcher policy file with a parameter out of its range: export refuses it in one line naming the parameter."""
    import json
    from tests.bad_inputs import crafted
    arrays, meta = _searcher_parts()
    meta = json.loads(json.dumps(meta))
    meta["params"][name] = value
    p = tmp_path / "s.npz"
    p.write_bytes(crafted(arrays, meta))
    msg = _export_refused(["--policy", str(p), "--out", str(tmp_path / "k.c"), *FAST], capsys)
    assert name in msg, msg
    assert not (tmp_path / "k.c").exists()


def test_searcher_checks_survive_python_O():
    """Under python -O (asserts stripped) a negative speed, a huge U-turn or run, a NaN alpha is still refused, naming the range."""
    import subprocess
    import sys
    from pathlib import Path
    code = ("from sim.baselines import SearcherParams\n"
            "for kw in ({'speed': -0.5}, {'uturn_steps': 10**9}, {'run_max_steps': 2**40}, {'run_alpha': float('nan')},\n"
            "           {'run_min_steps': float('inf')}):\n"
            "    try:\n        SearcherParams(**kw)\n    except ValueError as e:\n        print(e)\n")
    res = subprocess.run([sys.executable, "-O", "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == 5 and "speed must be in (0, 1]" in lines[0] and "uturn_steps must be in [0, 255]" in lines[1] \
        and "run_max_steps must be in [1, 65535]" in lines[2] and "run_alpha must be in [0.0, 1000.0]" in lines[3] \
        and "run_min_steps must be in [1.0, 65535.0]" in lines[4], res.stdout


def test_searcher_at_its_limits_runs_in_sim_and_export(tmp_path, capsys):
    """The largest parameters allowed (uint16 runs, 255-period turns, a tiny Pareto alpha) simulate and export without warnings."""
    import warnings
    from kiloforge.actors.searcher import quantize_searcher, searcher_policy
    from sim.baselines import HandWrittenSearcher, SearcherParams
    from sim.config import preset
    from sim.env import SwarmEnv
    from sim.rollout import rollout
    p = SearcherParams(run_min_steps=65535.0, run_max_steps=65535, run_alpha=1e-3, tumble_max_steps=255,
                       wall_turn_min=200, wall_turn_max=250, wall_cooldown=5, uturn_steps=255, settle_patience=254,
                       settle_hold=254)
    world = preset("kilobot")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rollout(SwarmEnv(world, 2, 3, seed=0), HandWrittenSearcher(world, p), 5, seed=1)
        q = quantize_searcher(searcher_policy(world, p))
    assert int(q.run_table.max()) == 65535


# --- world constants that would blind the RBF table (item 10) ----------------------------------------
def _bad_worlds(rng: np.random.Generator) -> list[dict]:
    """Generated RBF constants: widths and normalisers that underflow or overflow, normalisers that zero
    every feature, centres beyond the radius."""
    out = []
    for _ in range(3):
        out.append({"rbf_sigma_mm": float(10.0 ** -rng.uniform(4, 300))})  # 2 sigma^2 underflows, 0/0
        out.append({"rbf_norm": float(10.0 ** -rng.uniform(4, 300))})  # features overflow
        out.append({"rbf_norm": float(rng.uniform(129, 1e6))})  # every feature < 1/128: an all-zero table
        lo = float(rng.uniform(120, 250))
        out.append({"rbf_lo_mm": lo, "rbf_hi_mm": lo + float(rng.uniform(0, 50))})  # centres beyond the radius
    return out + [{"rbf_sigma_mm": 1e5}, {"rbf_hi_mm": 1e300}, {"rbf_norm": 1e300}]


BAD_WORLDS = _bad_worlds(np.random.default_rng(np.random.SeedSequence(4712)))


@pytest.mark.parametrize("change", BAD_WORLDS, ids=[",".join(f"{k}={v:.3g}" for k, v in c.items()) for c in BAD_WORLDS])
def test_world_that_blinds_the_rbf_table_is_refused(tmp_path, capsys, change):
    """A policy file whose world makes the RBF features NaN, infinite or all-zero in the firmware: one line, exit 2."""
    from tests.bad_inputs import crafted, parts, small_policy
    arrays, meta = parts(small_policy())
    meta["world"] = {**meta["world"], **change}
    p = tmp_path / "p.npz"
    p.write_bytes(crafted(arrays, meta))
    msg = _export_refused(["--policy", str(p), "--out", str(tmp_path / "k.c"), *FAST], capsys)
    assert "rbf" in msg.lower() and next(iter(change)) in msg or "RBF table would be all zero" in msg, msg
    assert not (tmp_path / "k.c").exists()


@pytest.mark.parametrize("change", BAD_WORLDS[:6], ids=[",".join(f"{k}={v:.3g}" for k, v in c.items())
                                                        for c in BAD_WORLDS[:6]])
def test_onnx_world_json_that_blinds_the_rbf_table_is_refused(tmp_path, capsys, change):
    """The same worlds given to the ONNX importer as --world-json: one line, exit 2."""
    import json
    from sim.config import preset
    model = tiny_model(tmp_path / "m.onnx", metadata=False)
    wj = tmp_path / "w.json"
    wj.write_text(json.dumps({"world": {**json.loads(preset("thesis").to_json()), **change}, "t_prev": 1}))
    msg = _export_refused(["--onnx", str(model), "--world-json", str(wj), "--out", str(tmp_path / "k.c"), *FAST],
                          capsys)
    assert "rbf" in msg.lower() or "RBF" in msg, msg


# --- work a policy file may ask for is capped by the command (item 12) --------------------------------
def _long_world_policy(tmp_path, steps: int):
    from tests.bad_inputs import crafted, parts, small_policy
    arrays, meta = parts(small_policy())
    meta["world"] = {**meta["world"], "episode_steps": steps}
    p = tmp_path / f"long{steps}.npz"
    p.write_bytes(crafted(arrays, meta))
    return p


LONG_STEPS = [10_001, 12_345, 250_000, 1_000_000]


@pytest.mark.parametrize("steps", LONG_STEPS)
def test_policy_world_cannot_set_a_long_calibration(tmp_path, capsys, steps):
    """A hash-valid policy whose world asks for a huge episode: export and export verify refuse at once, naming the cap and the flag."""
    from sim.config import FILE_STEPS_CAP
    p = _long_world_policy(tmp_path, steps)
    msg = _export_refused(["--policy", str(p), "--out", str(tmp_path / "k.c"), "--robots-calib", "2", "--quiet",
                           "--no-avr"], capsys)
    assert f"{FILE_STEPS_CAP:,}" in msg and "--calib-steps" in msg and f"{steps:,}" in msg
    msg = _export_refused(["verify", "--policy", str(p), "--robots", "2", "--episodes", "1", "--robots-calib", "2",
                           "--calib-steps", "3", "--quiet"], capsys)
    assert f"{FILE_STEPS_CAP:,}" in msg and "--steps" in msg


@pytest.mark.parametrize("steps,period", [(10_000, 32), (2_000, 255), (1_300, 240)])
def test_policy_world_cannot_set_long_tick_level_episodes(tmp_path, capsys, steps, period):
    """A tick-level world within the period cap but with long control periods: refused by its kilo_ticks, naming that cap."""
    from sim.config import FILE_TICKS_CAP
    from tests.bad_inputs import crafted, parts, small_policy
    arrays, meta = parts(small_policy())
    assert meta["world"]["tick_level"]
    meta["world"] = {**meta["world"], "episode_steps": steps, "period_ticks": period}
    p = tmp_path / "ticks.npz"
    p.write_bytes(crafted(arrays, meta))
    msg = _export_refused(["--policy", str(p), "--out", str(tmp_path / "k.c"), "--robots-calib", "2", "--quiet",
                           "--no-avr"], capsys)
    assert f"{FILE_TICKS_CAP:,}" in msg and f"{steps * period:,}" in msg and "--calib-steps" in msg


def test_flag_overrides_the_policy_world_length(tmp_path, capsys):
    """The same policy exports when the command is told the length (--calib-steps): the cap only guards the default."""
    p = _long_world_policy(tmp_path, LONG_STEPS[-1])
    assert export_main(["--policy", str(p), "--out", str(tmp_path / "k.c"), *FAST]) == 0
    capsys.readouterr()
    assert (tmp_path / "k.c").exists()


@pytest.mark.parametrize("steps", LONG_STEPS[:2])
def test_sim_caps_the_policy_world_length(tmp_path, capsys, steps):
    """python -m sim with such a policy: one line naming the cap and --steps; with --steps it runs."""
    from sim.__main__ import main as sim_main
    p = _long_world_policy(tmp_path, steps)
    rc = sim_main(["--policy", str(p), "--out", str(tmp_path / "o"), "--episodes", "1", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "--steps" in assert_one_clean_line(err) and "10,000" in err
    assert not (tmp_path / "o").exists()


# --- the host compiler from CC (item 13) --------------------------------------------------------------
def _write_exec(path, text: str, mode: int = 0o755):
    path.write_text(text)
    path.chmod(mode)
    return str(path)


BAD_CC = {
    "true": lambda d: "/bin/true",
    "false": lambda d: "false",
    "text file, not executable": lambda d: _write_exec(d / "cc.txt", "gcc\n", 0o644),
    "text file, executable, no interpreter": lambda d: _write_exec(d / "cc", "\x7fELF garbage\n"),
    "script writing nothing": lambda d: _write_exec(d / "cc.sh", "#!/bin/sh\nexit 0\n"),
    "script failing": lambda d: _write_exec(d / "cc2.sh", "#!/bin/sh\necho 'cc: fatal' >&2\nexit 3\n"),
    "a directory": lambda d: str(d),
    "missing program": lambda d: str(d / "no-such-cc"),
    "unbalanced quote": lambda d: 'gcc "-O2',
    "echo with flags": lambda d: "echo -n",
}


@pytest.mark.parametrize("how", sorted(BAD_CC))
def test_bad_cc_is_one_line(tmp_path, monkeypatch, capsys, how):
    """A CC that is not a working C compiler: export --verify host refuses in one line naming CC; nothing is written."""
    monkeypatch.setenv("CC", BAD_CC[how](tmp_path))
    msg = _export_refused(["--out", str(tmp_path / "k.c"), "--verify", "host", *FAST], capsys)
    assert "CC=" in msg and ("C compiler" in msg or "parsed" in msg), msg
    assert not (tmp_path / "k.c").exists()


def test_bad_cc_makes_simavr_a_documented_skip(tmp_path, monkeypatch):
    """With a CC that is not a compiler the simavr runner cannot be built: missing_tools says why (the export then uses the estimate)."""
    from export.verify import avr
    monkeypatch.setenv("CC", "/bin/true")
    why = avr.missing_tools(simulate=True)
    assert why is not None and "CC=" in why and "simavr runner" in why


@pytest.mark.parametrize("cc", ["gcc -O2", "  gcc   -std=c99 ", "gcc -Wno-unused-parameter", "'gcc' -O1"])
def test_cc_with_flags_is_split_like_a_shell(tmp_path, monkeypatch, capsys, cc):
    """CC with flags (quoted or padded) is the program plus its flags, and the host verification passes with it."""
    from export.verify.hostbuild import compiler
    import shutil
    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    monkeypatch.setenv("CC", cc)
    argv = compiler()
    assert argv is not None and argv[0] == shutil.which("gcc") and argv[1:] == cc.split()[1:]
    rc = export_main(["--out", str(tmp_path / "k.c"), "--verify", "host", *FAST])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "host build vs emulator: bit-exact" in out


# --- integers on the command line: ASCII decimal digits only (item 14) ---------------------------------
NOT_DECIMAL = ["\u0663", "1_0", "+3", "\uff13", "\U0001d7d1", "1 0", "0x10", "1e3", "3.0", "\u0969\u0966", "٣,5",
               "5,+6", "7,1_1", "", " ", "-", "١٢٣٤٥", "12\u200b3"]


@pytest.mark.parametrize("text", NOT_DECIMAL, ids=[ascii(t) for t in NOT_DECIMAL])
def test_target_uids_take_ascii_digits_only(tmp_path, capsys, text):
    """--target-uids with Unicode digits, underscores, a sign, hex or a float: one line, exit 2, nothing written."""
    msg = _export_refused(["--out", str(tmp_path / "k.c"), "--target-uids", text, *FAST], capsys)
    assert "--target-uids" in msg
    assert not (tmp_path / "k.c").exists()


@pytest.mark.parametrize("flag", ["--seed", "--calib-steps", "--calib-episodes", "--robots-calib"])
@pytest.mark.parametrize("text", ["\u0663", "1_0", "+3", "\uff14"], ids=ascii)
def test_every_integer_flag_takes_ascii_digits_only(tmp_path, capsys, flag, text):
    """Every integer flag goes through parse_decimal: the same strings are refused by name."""
    argv = [a for a in FAST if a not in ("--calib-steps", "4")] if flag == "--calib-steps" else list(FAST)
    if flag == "--robots-calib":
        argv = argv[2:]
    msg = _export_refused(["--out", str(tmp_path / "k.c"), *argv, flag, text], capsys)
    assert flag in msg


def test_parse_decimal_matches_int_on_ascii_only():
    """parse_decimal equals int() on ASCII decimal strings and refuses every other string int() accepts."""
    from kiloforge.validate import parse_decimal
    rng = np.random.default_rng(np.random.SeedSequence(4713))
    for v in rng.integers(-10 ** 18, 10 ** 18, size=200).tolist():
        assert parse_decimal(f" {v}\t") == v
    for digit in ("\u0660", "\u06f0", "\u0966", "\uff10", "\U0001d7ce"):  # zero of five Unicode digit sets
        text = "".join(chr(ord(digit) + int(c)) for c in "907")
        assert int(text) == 907
        with pytest.raises(ValueError):
            parse_decimal(text)
    for text in ("+1", "1_000", "0_1", " +0 "):
        int(text)
        with pytest.raises(ValueError):
            parse_decimal(text)


# --- rehash --out at a symbolic link writes through it (item 8) -------------------------------------
def _unhashed_policy(tmp_path):
    from tests.bad_inputs import crafted, parts, small_policy
    arrays, meta = parts(small_policy())
    p = tmp_path / "old.npz"
    p.write_bytes(crafted(arrays, meta, hashed=False))
    return p


@pytest.mark.parametrize("chain", [1, 2, 3])
@pytest.mark.parametrize("target_exists", [True, False])
def test_rehash_out_through_symlinks(tmp_path, capsys, chain, target_exists):
    """rehash --out LINK (a chain of 1-3 links; target present or not) replaces the file the link leads to; the links stay."""
    from kiloforge.policies import load_policy
    src = _unhashed_policy(tmp_path)
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "p.npz"
    if target_exists:
        target.write_bytes(b"old contents")
    links = [tmp_path / f"link{i}.npz" for i in range(chain)]
    for i, link in enumerate(links):
        link.symlink_to(target if i == chain - 1 else links[i + 1])
    assert export_main(["rehash", str(src), "--out", str(links[0])]) == 0, capsys.readouterr().err
    capsys.readouterr()
    assert all(link.is_symlink() for link in links)
    assert load_policy(target).hash == load_policy(links[0]).hash
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["p.npz"]  # no temporary left


def test_rehash_in_place_through_a_symlink(tmp_path, capsys):
    """rehash LINK (in place) re-hashes the file the link leads to and keeps the link."""
    from kiloforge.policies import load_policy
    src = _unhashed_policy(tmp_path)
    link = tmp_path / "link.npz"
    link.symlink_to(src)
    assert export_main(["rehash", str(link)]) == 0
    capsys.readouterr()
    assert link.is_symlink() and load_policy(src).hash


@pytest.mark.parametrize("how", ["loop", "to a directory", "into a missing directory"])
def test_rehash_out_bad_symlink_is_one_line(tmp_path, capsys, how):
    """A link loop, a link to a directory or into a missing directory: one line, exit 2, nothing changed."""
    src = _unhashed_policy(tmp_path)
    link = tmp_path / "out.npz"
    if how == "loop":
        (tmp_path / "b.npz").symlink_to(link)
        link.symlink_to(tmp_path / "b.npz")
    elif how == "to a directory":
        (tmp_path / "d").mkdir()
        link.symlink_to(tmp_path / "d")
    else:
        link.symlink_to(tmp_path / "missing" / "p.npz")
    before = sorted(p.name for p in tmp_path.iterdir())
    _export_refused(["rehash", str(src), "--out", str(link)], capsys)
    assert link.is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == before
