"""Training configuration: one documented dataclass, training presets, and validation.

The defaults are the thesis's MAGDDPG hyper-parameters (§4.3, §4.3.1), except the actor, which
has to run on a Kilobot: ``t_prev = 10`` and two hidden layers of 32 ELUs fit the ATmega328P
(checked against :mod:`export.codegen.budget`); the thesis's actor had four hidden layers on a 20-step
history. The thesis gives neither γ nor the layer widths (its Fig. 4.2 is not available to us): γ is
0.99 as in DDPG, and the critic has three hidden ELU layers of 256, 128 and 64 units.

Training presets (``--preset``; distinct from the *world* preset, ``--world``):

``default``  the thesis hyper-parameters: one environment, one update per transition, minibatch
             32, τ = 0.001, 500 warm-up + 10 000 learning episodes. Faithful and slow (days on a CPU).
``thesis``   ``default`` with the thesis's history length (20).
``fast``     tuned for wall clock on a small CPU: 16 environments in parallel, bigger minibatches,
             faster target tracking, higher learning rates (see ``TRAIN_PRESETS`` for the values
             and the README for why), and phantom neighbours (:mod:`learn.augment`) so that a
             policy trained with a few robots keeps working in large swarms.
``quick``    ``fast`` with a 5-minute budget and a small replay memory: learns something
             measurable (beats the random baseline) in minutes.
"""
from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass
from typing import Any

from sim.config import PRESETS as WORLD_PRESETS
from sim.config import WorldConfig
from sim.config import preset as world_preset


class ConfigError(ValueError):
    """A bad configuration value; the message is one line and says what to do."""


@dataclass
class TrainConfig:
    """Everything a MAGDDPG run depends on. Field docs double as ``--help`` text."""

    # --- task --------------------------------------------------------------------------------
    world: str = "thesis"  #: world preset (sim.config.PRESETS): thesis or kilobot
    n_robots: int = 4  #: robots trained together (thesis experiment 1: 1 to 8)
    t_prev: int = 10  #: history length T_prev in (previous action, observation) tuples
    episode_steps: int = 0  #: control steps per episode; 0 = the world's (thesis: 200)
    # --- networks ----------------------------------------------------------------------------
    actor_hidden: tuple[int, ...] = (32, 32)  #: actor hidden widths (ELU); must fit the Kilobot to export
    critic_hidden: tuple[int, ...] = (256, 128, 64)  #: critic hidden widths (ELU)
    # --- MAGDDPG -----------------------------------------------------------------------------
    gamma: float = 0.99  #: discount factor (not given in the thesis; 0.99 as in DDPG)
    tau: float = 0.001  #: soft target update rate
    lr_critic: float = 1e-3  #: Adam base learning rate of the critic
    lr_actor: float = 1e-4  #: Adam base learning rate of the actor
    batch_size: int = 32  #: minibatch size N
    replay_size: int = 500_000  #: replay memory capacity R in transitions
    warmup_episodes: int = 500  #: episodes (summed over envs) run with the initial policy before learning
    episodes: int = 10_000  #: learning episodes (summed over envs) after the warm-up
    updates_per_step: float = 1.0  #: gradient updates per collected transition (thesis: 1)
    reward_scale: float = 1.0  #: multiplies the world's reward for learning only (metrics stay raw)
    extra_action_penalty: float = 0.0  #: learning only: added to the world's action penalty (thesis 0.01)
    # --- exploration (Ornstein-Uhlenbeck, per robot and motor) -------------------------------
    noise_theta: float = 0.15  #: OU mean reversion per control step
    noise_sigma: float = 0.2  #: OU noise scale per control step
    noise_mu: float = 0.0  #: OU mean (added to the actor's action)
    phantom_neighbours: float = 0.0  #: training only: up to this many phantom neighbours per robot and step in the RBF histogram (learn/augment.py; 0 = off)
    # --- speed -------------------------------------------------------------------------------
    n_envs: int = 1  #: environments stepped together (each contributes one transition per step)
    threads: int = 1  #: torch CPU threads (1: on a shared 2-core CPU, 2 threads made updates 10-20x slower)
    # --- evaluation and bookkeeping ----------------------------------------------------------
    eval_every: int = 20_000  #: evaluate every this many transitions (at the next episode end)
    eval_episodes: int = 20  #: deterministic evaluation episodes (run as one vectorised batch)
    checkpoint_every: int = 1  #: write a checkpoint every this many evaluations (0 = only at the end)
    max_minutes: float = 0.0  #: stop at the first episode end after this wall-clock time (0 = no limit)
    seed: int = 1  #: master seed (networks, environments, noise, replay sampling, evaluation)
    exp_name: str = "default"  #: experiment name used in the default run directory name

    # ------------------------------------------------------------------------------------------
    def validate(self) -> "TrainConfig":
        """Raise :class:`ConfigError` (one line) for a bad value; return self."""

        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ConfigError(msg)

        need(self.world in WORLD_PRESETS,
             f"world must be one of {', '.join(sorted(WORLD_PRESETS))}, got '{self.world}'")
        need(1 <= self.n_robots <= 256, f"n_robots must be in 1..256, got {self.n_robots}")
        need(1 <= self.t_prev <= 200, f"t_prev (history) must be in 1..200, got {self.t_prev}")
        need(self.episode_steps >= 0, f"episode_steps must be >= 0 (0 = the world's), got {self.episode_steps}")
        for name in ("actor_hidden", "critic_hidden"):
            widths = getattr(self, name)
            need(len(widths) >= 1 and all(isinstance(w, int) and 1 <= w <= 4096 for w in widths),
                 f"{name} must be one or more widths in 1..4096, got {list(widths)}")
        need(0.0 <= self.gamma < 1.0, f"gamma must be in [0, 1), got {self.gamma}")
        need(0.0 < self.tau <= 1.0, f"tau must be in (0, 1], got {self.tau}")
        need(self.lr_critic > 0 and math.isfinite(self.lr_critic), f"lr_critic must be > 0, got {self.lr_critic}")
        need(self.lr_actor > 0 and math.isfinite(self.lr_actor), f"lr_actor must be > 0, got {self.lr_actor}")
        need(self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        need(self.warmup_episodes >= 0, f"warmup_episodes must be >= 0, got {self.warmup_episodes}")
        need(self.episodes >= 0, f"episodes must be >= 0, got {self.episodes}")
        need(self.updates_per_step >= 0 and math.isfinite(self.updates_per_step),
             f"updates_per_step must be >= 0, got {self.updates_per_step}")
        need(self.reward_scale > 0 and math.isfinite(self.reward_scale),
             f"reward_scale must be > 0, got {self.reward_scale}")
        need(self.extra_action_penalty >= 0 and math.isfinite(self.extra_action_penalty),
             f"extra_action_penalty must be >= 0, got {self.extra_action_penalty}")
        need(0 <= self.phantom_neighbours <= 1000, f"phantom_neighbours must be in [0, 1000], got {self.phantom_neighbours}")
        need(self.noise_theta >= 0, f"noise_theta must be >= 0, got {self.noise_theta}")
        need(self.noise_sigma >= 0, f"noise_sigma must be >= 0, got {self.noise_sigma}")
        need(1 <= self.n_envs <= 4096, f"n_envs must be in 1..4096, got {self.n_envs}")
        need(1 <= self.threads <= 256, f"threads must be in 1..256, got {self.threads}")
        need(self.eval_every >= 1, f"eval_every must be >= 1, got {self.eval_every}")
        need(self.eval_episodes >= 1, f"eval_episodes must be >= 1, got {self.eval_episodes}")
        need(self.checkpoint_every >= 0, f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        need(self.max_minutes >= 0, f"max_minutes must be >= 0, got {self.max_minutes}")
        need(0 <= self.seed < 2 ** 63, f"seed must be a non-negative integer, got {self.seed}")
        need(self.exp_name.replace("-", "").replace("_", "").replace(".", "").isalnum(),
             f"exp_name may hold letters, digits, '-', '_' and '.', got '{self.exp_name}'")
        steps = self.world_config().episode_steps
        need(self.replay_size >= steps * self.n_envs,
             f"replay_size ({self.replay_size}) must hold at least one episode per env "
             f"(episode_steps {steps} x n_envs {self.n_envs} = {steps * self.n_envs})")
        need(self.batch_size <= self.replay_size,
             f"batch_size ({self.batch_size}) must be <= replay_size ({self.replay_size})")
        return self

    # --- derived -----------------------------------------------------------------------------
    def world_config(self) -> WorldConfig:
        """The world this run trains in (world preset, with ``episode_steps`` when set)."""
        if self.episode_steps:
            return world_preset(self.world, episode_steps=self.episode_steps)
        return world_preset(self.world)

    @property
    def total_episodes(self) -> int:
        return self.warmup_episodes + self.episodes

    # --- (de)serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["actor_hidden"] = list(self.actor_hidden)
        d["critic_hidden"] = list(self.critic_hidden)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any], base: "TrainConfig | None" = None) -> "TrainConfig":
        """Fields of ``d`` replace those of ``base`` (default: the defaults); unknown keys are an error."""
        if not isinstance(d, dict):
            raise ConfigError(f"a training config must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - set(FIELD_TYPES))
        if unknown:
            raise ConfigError(f"unknown training config field(s): {', '.join(unknown)} "
                              f"(known: {', '.join(FIELD_TYPES)})")
        values = {k: coerce(k, v) for k, v in d.items()}
        return dataclasses.replace(base or cls(), **values)


FIELD_TYPES: dict[str, Any] = {f.name: f.type for f in dataclasses.fields(TrainConfig)}
_HINTS = typing.get_type_hints(TrainConfig)


def coerce(name: str, value: Any) -> Any:
    """Convert a JSON / CLI value to the field's type, with a one-line error naming the field."""
    hint = _HINTS[name]
    try:
        if hint is bool:
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(value)
                return value.lower() in ("true", "1", "yes")
            return bool(value)
        if hint is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(value)
            return int(value)
        if hint is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if hint is str:
            if not isinstance(value, str):
                raise ValueError(value)
            return value
        if typing.get_origin(hint) is tuple:
            if isinstance(value, (int, str)):
                value = [value]
            return tuple(coerce_int(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: cannot read {value!r} as {getattr(hint, '__name__', hint)}") from None
    raise ConfigError(f"{name}: unsupported field type {hint}")  # pragma: no cover


def coerce_int(v: Any) -> int:
    if isinstance(v, bool) or (isinstance(v, float) and not v.is_integer()):
        raise ValueError(v)
    return int(v)


#: Training presets: fields that differ from the defaults. ``fast`` departs from the thesis where
#: wall clock on a small CPU matters (see the module doc and README); every value is overridable.
TRAIN_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "thesis": {"t_prev": 20},
    "fast": {
        "n_envs": 16,
        "batch_size": 256,
        "tau": 0.005,
        "lr_critic": 1e-3,
        "lr_actor": 1e-3,
        "updates_per_step": 0.125,
        "warmup_episodes": 32,
        "episodes": 100_000,
        "replay_size": 200_000,
        "eval_every": 25_600,
        "eval_episodes": 50,
        "phantom_neighbours": 16.0,
        "exp_name": "fast",
    },
    "quick": {
        "n_envs": 16,
        "batch_size": 256,
        "tau": 0.005,
        "lr_critic": 1e-3,
        "lr_actor": 1e-3,
        "updates_per_step": 0.125,
        "warmup_episodes": 32,
        "episodes": 100_000,
        "replay_size": 100_000,
        "eval_every": 12_800,
        "eval_episodes": 50,
        "phantom_neighbours": 16.0,
        "max_minutes": 5.0,
        "exp_name": "quick",
    },
}


def from_preset(name: str, **overrides: Any) -> TrainConfig:
    """The training preset ``name`` with fields replaced (validated)."""
    if name not in TRAIN_PRESETS:
        raise ConfigError(f"unknown training preset '{name}'; choose one of: {', '.join(TRAIN_PRESETS)}")
    cfg = TrainConfig.from_dict({**TRAIN_PRESETS[name], **overrides})
    return cfg.validate()
