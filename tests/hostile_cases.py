"""Hostile inputs of issue 47 (parts A and B) run against an *installed* kiloforge, outside the repository.

tests/test_wheel.py copies this file into an empty directory and runs it with the fresh venv's Python, so it
imports nothing from tests/ and only the installed packages (numpy, no onnx). Each case runs the export
command in this process (``export.cli.main.main``) with a hostile input and checks the contract: exit 2 with
one stderr line saying what, or (a planted build runner) exit 0 without the planted program ever running.
Part B's cases run the ``kiloforge`` command (:func:`kiloforge.cli.main`, in this process, or as a program where
standard output must be a closed pipe or ``/dev/full``): names Matplotlib would read as mathtext and a name that is
not UTF-8 on every plot of ``sim``, a name too long for the file system, a run folder whose config is a list, a
weight beyond the int8 format. Prints one JSON line per case: ``{"case", "ok", "detail"}``; exits 1 if any case
broke the contract.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

FAST = ["--robots-calib", "2", "--calib-steps", "4", "--quiet"]


def _export(argv: list[str], env: dict[str, str] | None = None) -> tuple[int, str, str]:
    from export.cli.main import main

    saved = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return rc, out.getvalue(), err.getvalue()


def _refused(argv: list[str], must: str, env: dict[str, str] | None = None) -> tuple[bool, str]:
    rc, _, err = _export(argv, env)
    lines = [line for line in err.splitlines() if line.strip()]
    ok = rc == 2 and len(lines) == 1 and "Traceback" not in err and must in err
    return ok, f"rc {rc}: {err.strip()[:300]}"


def _kiloforge(argv: list[str]) -> tuple[int, str, str]:
    from kiloforge.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def _one_line(rc: int, err: str, must: str, status: int = 2) -> tuple[bool, str]:
    lines = [line for line in err.splitlines() if line.strip()]
    ok = rc == status and len(lines) == 1 and "Traceback" not in err and must in err
    return ok, f"rc {rc}: {err.strip()[:300]}"


def _shipped(name: str, dest: Path, scale_w0: float = 1.0) -> Path:
    """A copy of a shipped policy file (its first weight matrix scaled and the file re-hashed, if asked)."""
    from importlib import resources

    from kiloforge.artifact import artifact_bytes, read_artifact

    with resources.as_file(resources.files("export").joinpath("data", name)) as src:
        arrays, meta = read_artifact(src)
    meta = {k: v for k, v in meta.items() if k != "policy_hash"}
    arrays = dict(arrays, w0=arrays["w0"] * scale_w0) if scale_w0 != 1.0 else arrays
    dest.write_bytes(artifact_bytes(arrays, meta))
    return dest


def part_b_cases(work: Path) -> dict:
    """Part B: names, run folders, standard output, weights."""
    found = {}

    def plots_of_hostile_names():
        policy = _shipped("default_policy.npz", work / os.fsdecode(b"p$\\frac{1}{$\xff.npz"))
        rc, _, err = _kiloforge(["sim", "--policy", str(policy), "--out", str(work / "s$x$"), "--episodes", "1",
                                 "--steps", "3", "--quiet"])
        files = sorted(os.listdir(work / "s$x$")) if rc == 0 else []
        return rc == 0 and len(files) == 4, f"rc {rc}, {files}: {err.strip()[:300]}"

    def too_long_out():
        rc, _, err = _kiloforge(["export", "--out", str(work / ("n" * 300 + ".c")), "--no-avr", *FAST])
        return _one_line(rc, err, "bytes")

    def run_folder_config_a_list():
        run = work / "run"
        run.mkdir()
        (run / "config.json").write_text("[1, 2]")
        (run / "metrics.csv").write_text("env_steps,eval_return,eval_final_coverage\n1,2,0.5\n")
        rc, _, err = _kiloforge(["plot", str(run), "--out", str(work / "c.png")])
        return _one_line(rc, err, "config.json")

    def huge_weight():
        policy = _shipped("default_policy.npz", work / "huge.npz", 1e30)
        rc, _, err = _kiloforge(["export", "--policy", str(policy), "--out", str(work / "h.c"), "--no-avr", *FAST])
        return _one_line(rc, err, "int8")

    def closed_pipe():
        r, w = os.pipe()
        os.close(r)
        res = subprocess.run([sys.executable, "-m", "kiloforge", "--version"], stdout=w, stderr=subprocess.PIPE,
                             text=True, timeout=120)
        os.close(w)
        return res.returncode == 141 and res.stderr == "", f"rc {res.returncode}: {res.stderr.strip()[:300]}"

    def full_stdout():
        with open("/dev/full", "w") as full:
            res = subprocess.run([sys.executable, "-m", "export", "budget", "--hidden", "4", "--history", "2"],
                                 stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
        return _one_line(res.returncode, res.stderr, "standard output")

    found["mathtext and non-UTF-8 names on sim's plots"] = plots_of_hostile_names
    found["300-character --out"] = too_long_out
    found["run folder whose config.json is a list"] = run_folder_config_a_list
    found["weight 1e30 times the shipped one"] = huge_weight
    found["kiloforge --version into a closed pipe"] = closed_pipe
    found["export budget into /dev/full"] = full_stdout
    return found


def _policy_file(path: Path, world_change: dict | None = None, params_change: dict | None = None) -> Path:
    """The shipped searcher policy with its meta changed, re-hashed (a hash-valid hostile file)."""
    from importlib import resources

    from kiloforge.artifact import artifact_bytes, read_artifact

    with resources.as_file(resources.files("export").joinpath("data", "searcher_policy.npz")) as src:
        arrays, meta = read_artifact(src)
    meta = dict(meta)
    meta.pop("policy_hash", None)
    if world_change:
        meta["world"] = {**meta["world"], **world_change}
    if params_change:
        meta["params"] = {**meta["params"], **params_change}
    path.write_bytes(artifact_bytes(arrays, meta))
    return path


def _plant(path: Path, marker: Path) -> None:
    path.write_text(f"#!/bin/sh\necho planted >> '{marker}'\n")
    path.chmod(0o755)
    path.with_name(path.name + ".sha256").write_text(hashlib.sha256(path.read_bytes()).hexdigest() + "\n")


def cases(work: Path) -> dict:
    """name -> a function returning (ok, detail)."""
    out = str(work / "k.c")
    found = {}
    for text in ("\u0663", "1_0", "+3", "\uff17,2"):
        found[f"target-uids {ascii(text)}"] = lambda t=text: _refused(["--out", out, "--no-avr", *FAST,
                                                                       "--target-uids", t], "--target-uids")
    found["CC=/bin/true --verify host"] = lambda: _refused(["--out", out, "--no-avr", *FAST, "--verify", "host"],
                                                            "CC=", {"CC": "/bin/true"})
    found["searcher uturn_steps 10**9"] = lambda: _refused(
        ["--policy", str(_policy_file(work / "s1.npz", params_change={"uturn_steps": 10 ** 9})), "--out", out,
         "--no-avr", *FAST], "uturn_steps")
    found["world episode_steps 10**6"] = lambda: _refused(
        ["--policy", str(_policy_file(work / "s2.npz", world_change={"episode_steps": 10 ** 6})), "--out", out,
         "--no-avr", "--robots-calib", "2", "--quiet"], "10,000")
    found["world rbf_norm 1e-200"] = lambda: _refused(
        ["--policy", str(_policy_file(work / "s3.npz", world_change={"rbf_norm": 1e-200})), "--out", out,
         "--no-avr", *FAST], "rbf_norm")

    from export.verify import avr

    if avr.missing_tools(simulate=True) is None:
        def cache_is_a_file():
            f = work / "cache-file"
            f.write_text("x")
            return _refused(["--out", out, *FAST, "--verify", "avr"], "KILOFORGE_CACHE", {"KILOFORGE_CACHE": str(f)})

        def planted_default_cache():
            from export.verify import tools

            tmp = work / "tmp"
            tmp.mkdir()
            d = tmp / f"kiloforge-{os.geteuid()}"
            d.mkdir()
            marker = work / "planted-ran"
            _plant(d / f"{avr.RUNNER_NAME}-{avr.runner_key(tools.host_cc())}", marker)
            d.chmod(0o777)
            saved, tempfile.tempdir = tempfile.tempdir, str(tmp)
            cache = os.environ.pop("KILOFORGE_CACHE", None)
            try:
                rc, stdout, err = _export(["--out", str(work / "planted.c"), *FAST, "--verify", "avr"])
            finally:
                tempfile.tempdir = saved
                if cache is not None:
                    os.environ["KILOFORGE_CACHE"] = cache
            ok = rc == 0 and not marker.exists() and "bit-exact" in stdout
            return ok, f"rc {rc}, planted ran: {marker.exists()}: {err.strip()[:300]}"

        found["KILOFORGE_CACHE is a file"] = cache_is_a_file
        found["planted runner in a 0777 default cache"] = planted_default_cache
    return found


def main() -> int:
    bad = 0
    with tempfile.TemporaryDirectory(prefix="kf_hostile_") as td:
        for name, run in {**cases(Path(td)), **part_b_cases(Path(td))}.items():
            ok, detail = run()
            bad += not ok
            print(json.dumps({"case": name, "ok": ok, "detail": detail}), flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
