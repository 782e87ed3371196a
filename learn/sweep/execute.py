"""Running a sweep's trials on Ray Tune (imported only when trials run: Ray is an optional extra).

* Ray: a private local instance by default (``ray.init(address="local")`` with this machine's CPUs,
  or ``num_cpus``), or an existing cluster with ``address`` (``HOST:PORT`` or ``auto``). When Ray is
  already initialised (tests, notebooks) that instance is used and left running. Started by
  :func:`learn.es_pool.init_ray` (quiet, and keeping the driver's SIGINT / SIGTERM handlers).
* Tune: one trial per pending run directory (``tune.grid_search`` over them), each with
  ``cpus_per_trial`` CPUs (``tune.with_resources``); the Tune experiment lives in
  ``DIR/ray_tune/<name>``, its name a hash of the command's trials, so rerunning the same command
  restores it (``Tuner.restore(resume_unfinished=True, restart_errored=True)``). Either way a
  trial's own run directory decides what happens: finished trials return at once, unfinished ones
  resume from their checkpoints (:func:`learn.sweep.trial.run_trial`).
* Ctrl-C: Tune stops the trials and returns (their run directories keep their last checkpoint);
  the driver reports what is left and the same command resumes it.
* Progress: done / running / pending trials and the best evaluation return so far, as a tqdm bar
  on a terminal and one line per change otherwise. Ray's own console output is silenced with
  its documented switches (``RunConfig(verbose=0)``, ``RAY_AIR_NEW_OUTPUT=0``, ``log_to_driver=False``).
"""
from __future__ import annotations

import math
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # the legacy reporter, which verbose=0 silences fully

import ray  # noqa: E402
from ray import tune  # noqa: E402

from . import trial as tr  # noqa: E402
from .grid import Grid, Trial, digest  # noqa: E402

TUNE_DIR = "ray_tune"  #: Ray Tune's experiment directories inside the sweep directory


def _trainable(config: dict, sweep_dir: str = "", specs: dict | None = None, options: dict | None = None) -> None:
    """Tune's function trainable: the trial named ``config["trial"]`` through :func:`learn.sweep.trial.run_trial`."""
    t = specs[config["trial"]]
    options = dict(options or {})
    ev = options.pop("evaluation", None)
    tr.run_trial(t["trainer"], t["config"], Path(sweep_dir) / t["name"],
                 evaluation=None if ev is None else tr.EvalSpec(**ev), report=tune.report, **options)


def _trial_name(trial) -> str:
    return trial.config["trial"]


@dataclass
class Progress:
    """Counts and best return of the trials of one sweep, shown as a bar or as lines."""

    total: int
    done: int
    show: bool = True
    running: set = field(default_factory=set)
    failed: set = field(default_factory=set)
    best: tuple[float, str] = (-math.inf, "")
    _bar: object = None
    _last: str = ""

    def __post_init__(self) -> None:
        if self.show and sys.stderr.isatty():
            from kiloforge.progress import progress_bar

            self._bar = progress_bar(total=self.total, initial=self.done, unit="trial", desc="sweep",
                                     dynamic_ncols=True)
        self.refresh()

    def line(self) -> str:
        pending = self.total - self.done - len(self.running) - len(self.failed)
        s = f"{self.done}/{self.total} done, {len(self.running)} running, {pending} pending"
        if self.failed:
            s += f", {len(self.failed)} failed"
        if self.best[1]:
            s += f"; best return {self.best[0]:.2f} ({self.best[1]})"
        return s

    def refresh(self) -> None:
        text = self.line()
        if not self.show or text == self._last:
            return
        self._last = text
        if self._bar is not None:
            self._bar.n = self.done
            self._bar.set_postfix_str(text.split(" done, ", 1)[1], refresh=True)
        else:
            print(f"sweep: {text}", flush=True)

    def started(self, name: str) -> None:
        self.running.add(name)
        self.refresh()

    def result(self, name: str, result: dict) -> None:
        b = result.get("best_return")
        if isinstance(b, (int, float)) and math.isfinite(b) and b > self.best[0]:
            self.best = (float(b), name)
        self.refresh()

    def finished(self, name: str, ok: bool) -> None:
        self.running.discard(name)
        if ok:
            self.done += 1
        else:
            self.failed.add(name)
        self.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


_PROGRESS: Progress | None = None  # the driver's progress; the callback below holds no state of its own


class _ProgressCallback(tune.Callback):
    """Forwards Tune's trial events to the current :class:`Progress` (stateless: Tune pickles it into
    its experiment, and a restored experiment must report to the new driver's progress)."""

    def on_trial_start(self, iteration, trials, trial, **info):
        if _PROGRESS is not None:
            _PROGRESS.started(_trial_name(trial))

    def on_trial_result(self, iteration, trials, trial, result, **info):
        if _PROGRESS is not None:
            _PROGRESS.result(_trial_name(trial), result)

    def on_trial_complete(self, iteration, trials, trial, **info):
        if _PROGRESS is not None:
            _PROGRESS.finished(_trial_name(trial), True)

    def on_trial_error(self, iteration, trials, trial, **info):
        if _PROGRESS is not None:
            _PROGRESS.finished(_trial_name(trial), False)


def init_ray(address: str | None, num_cpus: int | None) -> bool:
    """Start or join Ray unless it is initialised; True when this call did (and should shut it down)."""
    if ray.is_initialized():
        return False
    from ..es_pool import init_ray as start

    start(ray, address or "", num_cpus, "--address")
    return True


@dataclass
class Outcome:
    """What one sweep run did."""

    ran: int  # trials given to Tune
    errors: dict[str, str]  # trial name → first line of its error


def run_trials(sweep_dir: Path, grid: Grid, trials: list[Trial], pending: list[Trial], done: int,
               address: str | None = None, num_cpus: int | None = None, progress: bool = True,
               log: Callable[[str], None] = print) -> Outcome:
    """Run ``pending`` (a subset of ``trials``, the command's trials) on Ray Tune; see the module doc."""
    global _PROGRESS
    own = init_ray(address, num_cpus)
    try:
        cpus = ray.cluster_resources().get("CPU", 0)
        if grid.cpus_per_trial > cpus:  # an autoscaling cluster may still grow
            log(f"warning: --cpus-per-trial {grid.cpus_per_trial:g} is more than the {cpus:g} CPUs of the Ray "
                f"cluster; its trials wait until the cluster grows")
        storage = (sweep_dir / TUNE_DIR).resolve()
        name = f"sweep-{digest(sorted(t.name for t in trials))}"
        options = {"budget_minutes": grid.max_minutes, "threads": max(1, int(grid.cpus_per_trial)),
                   "evaluation": None if grid.evaluation is None else grid.to_dict()["evaluation"]}
        trainable = tune.with_resources(
            tune.with_parameters(_trainable, sweep_dir=str(sweep_dir.resolve()),
                                 specs={t.name: t.to_dict() for t in trials}, options=options),
            {"cpu": grid.cpus_per_trial})
        tuner = _restorable(storage / name, trainable, {t.name for t in pending}, log)
        if tuner is None:
            tuner = tune.Tuner(
                trainable,
                param_space={"trial": tune.grid_search([t.name for t in pending])},
                tune_config=tune.TuneConfig(trial_name_creator=_trial_name, trial_dirname_creator=_trial_name),
                run_config=tune.RunConfig(name=name, storage_path=str(storage), verbose=0,
                                          failure_config=tune.FailureConfig(max_failures=0),
                                          callbacks=[_ProgressCallback()]))
        _PROGRESS = Progress(total=len(trials), done=done, show=progress)
        try:
            results = tuner.fit()
        finally:
            _PROGRESS.close()
            _PROGRESS = None
        errors = {}
        for r in results:
            if r.error is not None and "TrialInterrupted" not in str(r.error):  # interrupted: resumable
                n = Path(r.path).name
                errors[n] = (str(r.error).strip().splitlines() or [type(r.error).__name__])[-1]
        return Outcome(len(pending), errors)
    finally:
        if own:
            ray.shutdown()


def _restorable(path: Path, trainable, pending: set[str], log: Callable[[str], None]):
    """The Tune experiment at ``path`` restored, if it exists and would run every pending trial."""
    if not tune.Tuner.can_restore(str(path)):
        return None
    try:
        tuner = tune.Tuner.restore(str(path), trainable, resume_unfinished=True, restart_errored=True)
        known = {Path(r.path).name: r.error is None and bool(r.metrics.get("finished"))  # dir name = trial name
                 for r in tuner.get_results()}
    except Exception as e:  # noqa: BLE001 - the run directories, not Tune's state, say what is left to do
        log(f"note: cannot restore the Tune experiment {path} ({type(e).__name__}: {e}); starting it afresh")
        shutil.rmtree(path)
        return None
    missed = sorted(n for n in pending if known.get(n, True))
    if missed:  # e.g. a finished run directory was removed: Tune would not run it again
        log(f"note: {len(missed)} trial(s) to run are finished or unknown in {path}; starting it afresh")
        shutil.rmtree(path)
        return None
    return tuner
