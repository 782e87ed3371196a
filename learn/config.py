"""Training configurations: one documented dataclass per algorithm, training presets, validation.

* :class:`ExperimentConfig` — what the one experiment loop (:mod:`learn.train`) needs whatever the
  actor: task, critic, the DDPG hyper-parameters, exploration, guidance by demonstrations, speed and
  bookkeeping. Not used on its own.
* :class:`TrainConfig` — **MAGDDPG** (thesis Algorithm 4): a feed-forward (MLP) actor over the
  ``t_prev`` history of (previous action, observation) tuples, minibatches of transitions.
* :class:`RecurrentConfig` — **MAGRDPG** (thesis Algorithm 5): a recurrent actor (GRU or LSTM) over one tuple
  per step, minibatches of burn-in + unroll windows.

Every field is a command-line option (:mod:`learn.cli`, tyro); its ``#:`` comment is the help text.
``to_dict`` / ``from_dict`` round-trip through JSON; ``from_dict`` refuses unknown fields and values
of the wrong type with one line (:mod:`kiloforge.validate`'s checks).

The MAGDDPG defaults are the thesis's hyper-parameters (§4.3, §4.3.1), except the actor, which has
to run on a Kilobot: ``t_prev = 10`` and two hidden layers of 32 ELUs fit the ATmega328P (checked
against the exporter's budget); the thesis's actor had four hidden layers on a 20-step history. The
thesis gives neither γ nor the layer widths: γ is 0.99 as in DDPG, and the critic has three hidden ELU
layers of 256, 128 and 64 units.

Training presets (``--preset``; distinct from the *world*, ``--world``), in ``TRAIN_PRESETS``
(MAGDDPG) and ``RECURRENT_PRESETS`` (MAGRDPG):

``default``  MAGDDPG with the thesis hyper-parameters: one environment, one update per transition,
             minibatch 32, τ = 0.001, 500 warm-up + 10 000 learning episodes (days on a CPU).
``thesis``   ``default`` with the thesis's history length (20).
``fast``     tuned for wall clock on a small CPU: 16 environments, bigger minibatches, faster target
             tracking, higher learning rates, phantom neighbours (:mod:`learn.augment`), the owed updates
             in blocks every 8 env steps, the actor on every other update and, above 4 robots, its objective on
             4 robots per sample; 50 evaluation episodes every 51 200 transitions (evaluation ≈ 5 % of the wall
             clock).
``quick``    ``guided`` in minutes: 128 demonstration episodes, 1,000 cloning steps, a 5-minute budget and a
             small replay memory.
``guided``   ``fast`` (updates after every env step, the actor on every update and robot) started from demonstrations of the hand-written searcher (:mod:`learn.demos`):
             behaviour cloning, a critic-only phase, small BC-anchored actor steps through ``clip``
             action gradients (README: guided training).
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import typing
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import tyro

from kiloforge.errors import InputError
from kiloforge.validate import check_int, check_real, check_str, check_typed, show
from sim.config import BENCHMARK_STEPS, DEFAULT_WORLD, MAX_EPISODE_STEPS, MAX_ROBOTS
from sim.config import PRESETS as WORLD_PRESETS
from sim.config import WorldConfig
from sim.variants import RANDOMISATIONS as NAMED_RANDOMISATIONS
from sim.config import preset as world_preset
from sim.tasks import DEFAULT_TASK, Task, get_task


class ConfigError(ValueError):
    """A bad configuration value; the message is one line and says what to do."""


ACTION_GRADIENTS = ("invert", "clip")  #: values of ``action_gradient``
PRECISIONS = ("fp32", "bf16")  #: values of ``precision`` (the arithmetic of the updates)
ACTOR_OTHERS = ("policy", "replay")  #: values of ``actor_others``
CRITICS = ("concat", "mean", "robot")  #: values of ``critic``
CRITIC_POOLS = ("mean", "meanmax")  #: values of ``critic_pool``
REWARDS = ("team", "linear", "potential", "local")  #: values of ``reward`` (learn.rewards)
SIZE_MIXES = ("equal", "robots")  #: values of ``size_mix``
DEVICES = ("auto", "cpu", "cuda")  #: values of ``device``
DEMO_POLICIES = ("none", "searcher", "pusher")  #: values of ``demo_policy`` (learn.demos)
CELLS = ("gru", "lstm")  #: recurrent cells of RecurrentConfig.cell (learn.recurrent.RECURRENT_ACTORS)
MAX_TEXT_FIELD = 4096  #: characters of a str field (a path, a name) in a config file

#: config fields whose flag is not ``--field-name`` but a shorter alias (both work)
FLAG_ALIASES = {"n_robots": "--robots", "t_prev": "--history"}
Robots = Annotated[tuple[int, ...], tyro.conf.arg(aliases=(FLAG_ALIASES["n_robots"],))]
HistoryLength = Annotated[int, tyro.conf.arg(aliases=(FLAG_ALIASES["t_prev"],))]




def choice(values: typing.Iterable[str]) -> Any:
    """A str field taking one of ``values``, which its ``--help`` lists (``--world {kilobot,thesis}``)."""
    return Annotated[str, tyro.conf.arg(metavar="{" + ",".join(values) + "}")]


World = choice(sorted(WORLD_PRESETS))
Randomise = choice(dict.fromkeys(["none", *NAMED_RANDOMISATIONS]))
DemoPolicy = choice(DEMO_POLICIES)


def flag_name(field: str) -> str:
    """The flag a user types for a config field: ``lr_actor`` → ``--lr-actor``, ``n_robots`` → ``--robots``."""
    return FLAG_ALIASES.get(field, "--" + field.replace("_", "-"))



class ConfigBase:
    """What every algorithm's config shares: tuple fields, the world, JSON round trip (not used on its own)."""

    algorithm: ClassVar[str] = ""

    def __post_init__(self) -> None:
        if isinstance(self.n_robots, int) and not isinstance(self.n_robots, bool):
            self.n_robots = (self.n_robots,)
        for name in self._tuple_fields():
            value = getattr(self, name)
            if isinstance(value, list):
                setattr(self, name, tuple(value))

    @classmethod
    def _tuple_fields(cls) -> tuple[str, ...]:
        return tuple(f for f, h in _hints(cls).items() if typing.get_origin(h) is tuple)

    def task_spec(self) -> Task:
        """The task this run trains for (:func:`sim.tasks.get_task` of ``task``)."""
        return get_task(self.task)

    def check_task(self) -> None:
        """The task resolves, runs in the world, and demonstrations (localisation's searcher) only go with localisation."""
        try:
            task = self.task_spec()
            task.check_world(self.world_config())
        except ValueError as e:
            raise ConfigError(str(e)) from None
        need(self.demo_policy == "none" or task.name == DEFAULT_TASK,
             f"demo_policy '{self.demo_policy}' demonstrates localisation, not task '{task.name}': "
             "use --demo-policy none (random initial weights)")

    def world_config(self) -> WorldConfig:
        """The world this run trains in: the world preset (with ``episode_steps`` when set) with the task's bodies
        and observation layout (:meth:`sim.tasks.Task.world`)."""
        world = world_preset(self.world, episode_steps=self.episode_steps) if self.episode_steps else world_preset(self.world)
        return self.task_spec().world(world)

    # --- (de)serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields and the algorithm; one swarm size is written as an integer."""
        d = {"algorithm": self.algorithm, **dataclasses.asdict(self)}
        d = {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
        if len(self.n_robots) == 1:
            d["n_robots"] = self.n_robots[0]
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any], base: "ConfigBase | None" = None):
        """Fields of ``d`` replace those of ``base`` (default: the defaults); unknown keys and values of
        the wrong type are an error (one line naming the field). Not validated: call ``validate()``."""
        if not isinstance(d, dict):
            raise ConfigError(f"a training config must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        algo = d.pop("algorithm", cls.algorithm)
        if algo != cls.algorithm:
            raise ConfigError(f"this is a {algo} config, not {cls.algorithm}")
        hints = _hints(cls)
        unknown = sorted(set(d) - set(hints))
        if unknown:
            raise ConfigError(f"unknown training config field(s): {', '.join(unknown)} "
                              f"({cls.algorithm}; known: {', '.join(hints)})")
        return dataclasses.replace(base or cls(), **{k: check_type(cls, k, v) for k, v in d.items()})


@dataclass
class ExperimentConfig(ConfigBase):
    """Fields of every algorithm (see the module doc); use TrainConfig or RecurrentConfig."""

    algorithm: ClassVar[str] = ""

    # --- task --------------------------------------------------------------------------------
    world: World = DEFAULT_WORLD  #: world preset (sim.config.PRESETS): kilobot (the robots') or thesis
    n_robots: Robots = (4,)  #: swarm sizes trained together (one env group and replay per size; > 1 needs --critic mean)
    episode_steps: int = 0  #: control steps per episode; 0 = the world's (kilobot: 300, thesis: 200)
    randomise: Randomise = "none"  #: domain randomisation of the training envs (a name in sim.variants.RANDOMISATIONS)
    randomise_eval: bool = False  #: also randomise the evaluation envs
    reward: choice(REWARDS) = "team"  #: learning reward: team (the world's), linear (the task's success, not squared), potential (team + shaping), local (each robot's own success; needs --critic robot)
    shaping_weight: float = 1.0  #: weight of the potential-based shaping term (reward potential)
    # --- critic ------------------------------------------------------------------------------
    critic: choice(CRITICS) = "concat"  #: centralised critic: concat (thesis: full state + joint action), mean (mean embedding, any swarm size) or robot (the mean critic with one value per robot: its own features beside the mean embedding)
    critic_hidden: tuple[int, ...] = (256, 128, 64)  #: critic hidden widths (ELU); the mean critic's head after pooling
    critic_embed: tuple[int, ...] = (64, 64)  #: mean critic: per-robot encoder widths (ELU)
    critic_pool: choice(CRITIC_POOLS) = "mean"  #: mean critic pooling over robots: mean or meanmax
    critic_obs: bool = False  #: mean critic: also encode each robot's observation
    # --- actor-critic updates ----------------------------------------------------------------
    gamma: float = 0.99  #: discount factor (not given in the thesis; 0.99 as in DDPG)
    tau: float = 0.001  #: soft target update rate
    lr_critic: float = 1e-3  #: Adam learning rate of the critic
    lr_actor: float = 1e-4  #: Adam learning rate of the actor
    grad_clip: float = 0.0  #: clip the actor's gradient norm to this (0 = no clipping)
    #: how ∇_a Q reaches a bounded action: invert (inverting gradients, thesis §4.3.1) or clip (the
    #: gradient of Q(s, clip(a)): zero beyond the bounds, so commands at 0 or 1 are not ratcheted inwards)
    action_gradient: choice(ACTION_GRADIENTS) = "invert"
    actor_robots: int = 0  #: actor objective on this many random robots per sample, scaled to all (0 = every robot)
    #: with actor_robots: the other robots' actions in Q come from the current actor without gradient (policy:
    #: an unbiased estimate of the full gradient) or from the replay (replay: as MADDPG; cheaper, a different objective)
    actor_others: choice(ACTOR_OTHERS) = "policy"
    replay_size: int = 500_000  #: replay capacity in transitions per swarm size (whole episodes)
    warmup_episodes: int = 500  #: episodes (summed over envs) run with the initial policy before learning
    episodes: int = 10_000  #: learning episodes (summed over envs and sizes) after the warm-up
    updates_per_step: float = 1.0  #: gradient updates per collected transition (thesis: 1)
    update_every: int = 1  #: owed updates run in blocks every this many env steps (and at episode ends)
    #: the actor and its target step on every this many-th update, the critic on every one (TD3's delayed
    #: policy updates, Fujimoto et al. 2018; 1 = every update): fewer actor and actor-objective passes
    policy_every: int = 1
    size_mix: choice(SIZE_MIXES) = "equal"  #: share of a minibatch per swarm size: equal, or robots (proportional to robot count)
    reward_scale: float = 1.0  #: multiplies the learning reward (metrics stay raw)
    extra_action_penalty: float = 0.0  #: learning only: added to the world's action penalty (thesis 0.01)
    # --- exploration (Ornstein-Uhlenbeck, per robot and motor) -------------------------------
    noise_theta: float = 0.15  #: OU mean reversion per control step
    noise_sigma: float = 0.2  #: OU noise scale per control step
    noise_mu: float = 0.0  #: OU mean (added to the actor's action)
    phantom_neighbours: float = 0.0  #: training only: up to this many phantom neighbours per robot and step (learn/augment.py; 0 = off)
    # --- guidance by demonstrations (learn.demos) --------------------------------------------
    demo_policy: DemoPolicy = "none"  #: demonstrator: none, searcher or pusher (hand-written, learn.demos)
    demo_episodes: int = 1024  #: demonstrator episodes per swarm size, collected before training
    bc_updates: int = 1500  #: behaviour-cloning steps of the actor on the demonstrations before RL
    bc_lr: float = 3e-3  #: Adam learning rate of behaviour cloning
    bc_weight: float = 1.0  #: weight of the Q-filtered behaviour-cloning loss during RL (0 = none)
    actor_delay: int = 0  #: the first this many updates train only the critic (keeps a cloned actor intact)
    critic_pretrain: int = 0  #: critic-only updates on the demonstrations after cloning
    # --- speed -------------------------------------------------------------------------------
    n_envs: int = 1  #: environments stepped together per swarm size
    #: torch CPU threads; 0 = auto: 1, and for the update blocks 1 or every core (at most 4), whichever is measured
    #: faster, only where that gives the same bits (learn.speed); N = N threads everywhere
    threads: int = 0
    device: choice(DEVICES) = "auto"  #: networks and replay on cpu or cuda; auto = cuda when available (the env stays NumPy)
    #: arithmetic of the updates: fp32, or bf16 (hidden layers in a bfloat16 autocast, outputs, losses and weights
    #: float32; 1.2-1.3x faster updates at 32 robots on a CPU with AVX-512 bf16, none at 4; changes what is learned)
    precision: choice(PRECISIONS) = "fp32"
    # --- evaluation and bookkeeping ----------------------------------------------------------
    eval_every: int = 20_000  #: evaluate every this many transitions (at the next episode end)
    eval_episodes: int = 20  #: deterministic evaluation episodes per swarm size
    checkpoint_every: int = 1  #: write a checkpoint every this many evaluations (0 = only at the end)
    max_minutes: float = 0.0  #: stop at the first episode end after this wall-clock time (0 = no limit)
    tensorboard: bool = False  #: also log every metrics row as TensorBoard scalars (run_dir/tensorboard)
    seed: int = 1  #: master seed (networks, environments, noise, replay sampling, evaluation)
    exp_name: str = "default"  #: experiment name used in the default run directory name
    task: str = "localisation"  #: the task (sim.tasks): a built-in or plug-in name, or path/to/file.py:ClassName

    # --- validation ----------------------------------------------------------------------------
    def validate(self) -> "ExperimentConfig":
        """Raise :class:`ConfigError` (one line) for a bad value; return self."""
        need(self.world in WORLD_PRESETS, f"world must be one of {', '.join(sorted(WORLD_PRESETS))}, got '{self.world}'")
        self.check_task()
        need(len(self.n_robots) >= 1 and all(isinstance(m, int) and 1 <= m <= MAX_ROBOTS for m in self.n_robots),
             f"n_robots must be in 1..{MAX_ROBOTS}, got {_show(self.n_robots)}")
        need(len(set(self.n_robots)) == len(self.n_robots), f"n_robots lists a size twice: {_show(self.n_robots)}")
        need(len(self.n_robots) == 1 or self.critic != "concat",
             f"training on several swarm sizes ({_show(self.n_robots)}) needs --critic mean or robot "
             "(the concatenating critic's input depends on the robot count)")
        need(self.episode_steps >= 0, f"episode_steps must be >= 0 (0 = the world's), got {self.episode_steps}")
        need(self.reward in REWARDS, f"reward must be one of {', '.join(REWARDS)}, got '{self.reward}'")
        need(math.isfinite(self.shaping_weight), f"shaping_weight must be finite, got {self.shaping_weight}")
        need(self.critic in CRITICS, f"critic must be one of {', '.join(CRITICS)}, got '{self.critic}'")
        need(self.reward != "local" or self.critic == "robot",
             "--reward local pays each robot its own reward and needs the per-robot critic (--critic robot)")
        need(self.reward != "local" or self.demo_policy == "none",
             "--reward local learns from scratch: demonstrations store the team reward (use --demo-policy none)")
        need(self.critic_pool in CRITIC_POOLS, f"critic_pool must be one of {', '.join(CRITIC_POOLS)}, got '{self.critic_pool}'")
        for name in (f for f in self._tuple_fields() if f != "n_robots"):
            widths = getattr(self, name)
            need(len(widths) >= 1 and all(isinstance(w, int) and 1 <= w <= 4096 for w in widths),
                 f"{name} must be one or more widths in 1..4096, got {list(widths)}")
        need(0.0 <= self.gamma < 1.0, f"gamma must be in [0, 1), got {self.gamma}")
        need(0.0 < self.tau <= 1.0, f"tau must be in (0, 1], got {self.tau}")
        for name in ("lr_critic", "lr_actor", "reward_scale", "bc_lr"):
            v = getattr(self, name)
            need(v > 0 and math.isfinite(v), f"{name} must be > 0, got {v}")
        for name in ("grad_clip", "extra_action_penalty", "updates_per_step", "noise_theta", "noise_sigma",
                     "bc_weight", "max_minutes"):
            v = getattr(self, name)
            need(v >= 0 and math.isfinite(v), f"{name} must be >= 0, got {v}")
        need(math.isfinite(self.noise_mu), f"noise_mu must be finite, got {self.noise_mu}")
        need(self.action_gradient in ACTION_GRADIENTS,
             f"action_gradient must be one of {', '.join(ACTION_GRADIENTS)}, got '{self.action_gradient}'")
        need(0 <= self.actor_robots <= MAX_ROBOTS, f"actor_robots must be in 0..{MAX_ROBOTS}, got {self.actor_robots}")
        need(self.actor_others in ACTOR_OTHERS,
             f"actor_others must be one of {', '.join(ACTOR_OTHERS)}, got '{self.actor_others}'")
        need(self.warmup_episodes >= 0, f"warmup_episodes must be >= 0, got {self.warmup_episodes}")
        need(self.episodes >= 0, f"episodes must be >= 0, got {self.episodes}")
        need(self.update_every >= 1, f"update_every must be >= 1, got {self.update_every}")
        need(1 <= self.policy_every <= 1000, f"policy_every must be in 1..1000, got {self.policy_every}")
        need(self.size_mix in SIZE_MIXES, f"size_mix must be one of {', '.join(SIZE_MIXES)}, got '{self.size_mix}'")
        need(0 <= self.phantom_neighbours <= 1000, f"phantom_neighbours must be in [0, 1000], got {self.phantom_neighbours}")
        need(self.demo_policy in DEMO_POLICIES,
             f"demo_policy must be one of {', '.join(DEMO_POLICIES)}, got '{self.demo_policy}'")
        need(self.demo_episodes >= 1, f"demo_episodes must be >= 1, got {self.demo_episodes}")
        for name in ("bc_updates", "actor_delay", "critic_pretrain"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        need(1 <= self.n_envs <= 4096, f"n_envs must be in 1..4096, got {self.n_envs}")
        need(0 <= self.threads <= 256, f"threads must be in 0..256 (0 = auto), got {self.threads}")
        need(self.device in DEVICES, f"device must be one of {', '.join(DEVICES)}, got '{self.device}'")
        need(self.precision in PRECISIONS, f"precision must be one of {', '.join(PRECISIONS)}, got '{self.precision}'")
        need(self.eval_every >= 1, f"eval_every must be >= 1, got {self.eval_every}")
        need(self.eval_episodes >= 1, f"eval_episodes must be >= 1, got {self.eval_episodes}")
        need(self.checkpoint_every >= 0, f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        need(0 <= self.seed < 2 ** 63, f"seed must be a non-negative integer, got {self.seed}")
        need(re.fullmatch(r"[A-Za-z0-9._-]+", self.exp_name) is not None,
             f"exp_name may hold letters, digits, '-', '_' and '.', got '{self.exp_name}'")
        if self.randomise != "none":
            randomisation(self.randomise)  # ConfigError for an unknown name
        steps = self.world_config().episode_steps
        need(self.replay_size >= steps * self.n_envs,
             f"replay_size ({self.replay_size}) must hold at least one episode per env "
             f"(episode_steps {steps} x n_envs {self.n_envs} = {steps * self.n_envs})")
        return self

    # --- derived -------------------------------------------------------------------------------
    @property
    def total_episodes(self) -> int:
        return self.warmup_episodes + self.episodes

    @property
    def batch_samples(self) -> int:
        """Samples per minibatch (transitions or windows) drawn from the learner's replay."""
        raise NotImplementedError

    @property
    def demo_samples(self) -> int:
        """Demonstration samples added to every minibatch (0 without a demonstrator)."""
        raise NotImplementedError

@dataclass
class TrainConfig(ExperimentConfig):
    """MAGDDPG: an MLP actor over the T_prev history (thesis Algorithm 4). Field docs double as --help."""

    algorithm: ClassVar[str] = "magddpg"

    t_prev: HistoryLength = 10  #: history length T_prev in (previous action, observation) tuples
    actor_hidden: tuple[int, ...] = (32, 32)  #: actor hidden widths (ELU); must fit the Kilobot to export
    batch_size: int = 32  #: minibatch size in transitions (per update, summed over swarm sizes)
    demo_transitions: int = 32  #: demonstration transitions added to every minibatch (with a demonstrator)

    def validate(self) -> "TrainConfig":
        super().validate()
        need(1 <= self.t_prev <= 200, f"t_prev must be in 1..200, got {self.t_prev}")
        need(self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        need(self.batch_size <= self.replay_size,
             f"batch_size ({self.batch_size}) must be <= replay_size ({self.replay_size})")
        need(self.demo_transitions >= 0, f"demo_transitions must be >= 0, got {self.demo_transitions}")
        return self

    @property
    def batch_samples(self) -> int:
        return self.batch_size

    def budget_note(self) -> str | None:
        """Why the exporter would refuse this actor (None when it fits the Kilobot)."""
        from export.codegen.budget import estimate
        from kiloforge.actors.mlp import MLP, MLPArch

        b = estimate(MLP, self.world_config(), MLPArch(self.t_prev, tuple(self.actor_hidden)))
        return None if b.ok else (f"this actor (t_prev {self.t_prev}, hidden {list(self.actor_hidden)}) does not "
                                  f"fit the Kilobot budget ({b.summary()})")

    @property
    def demo_samples(self) -> int:
        return self.demo_transitions if self.demo_policy != "none" else 0


@dataclass
class RecurrentConfig(ExperimentConfig):
    """MAGRDPG: a recurrent actor over one tuple per step (thesis Algorithm 5). Field docs double as --help."""

    algorithm: ClassVar[str] = "magrdpg"

    n_robots: Robots = (2,)  #: swarm sizes trained together (one env group and replay per size; > 1 needs --critic mean)
    tau: float = 0.005  #: soft target update rate
    lr_actor: float = 3e-4  #: Adam learning rate of the actor (1e-3, MAGDDPG's fast value, was less stable)
    grad_clip: float = 1.0  #: clip the actor's gradient norm to this (0 = no clipping)
    replay_size: int = 200_000  #: replay capacity in transitions per swarm size (whole episodes)
    warmup_episodes: int = 32  #: episodes (summed over envs) with the initial policy before learning
    episodes: int = 100_000  #: learning episodes (summed over envs and sizes) after the warm-up
    updates_per_step: float = 0.125  #: gradient updates per collected transition
    n_envs: int = 16  #: environments stepped together per swarm size
    eval_every: int = 25_600  #: evaluate every this many transitions (at the next episode end)
    exp_name: str = "gru"  #: experiment name used in the default run directory name

    cell: choice(CELLS) = "gru"  #: the actor's recurrent cell: gru or lstm (the thesis's MAGRDPG used an LSTM)
    hidden: int = 32  #: recurrent units of the actor (the firmware keeps them as int8 in SRAM)
    unroll: int = 8  #: T_unroll: steps per window with loss and gradient (truncated BPTT length)
    burn_in: int = 8  #: steps before them that only warm up the hidden state from zero
    batch_windows: int = 32  #: windows per minibatch (critic samples = batch_windows x unroll)
    demo_windows: int = 8  #: demonstration windows added to every minibatch (with a demonstrator)

    def validate(self) -> "RecurrentConfig":
        super().validate()
        need(self.cell in CELLS, f"cell must be one of {', '.join(CELLS)}, got '{self.cell}'")
        need(1 <= self.hidden <= 255, f"hidden must be in 1..255 (uint8 index in the firmware), got {self.hidden}")
        need(self.unroll >= 1, f"unroll must be >= 1, got {self.unroll}")
        need(self.burn_in >= 0, f"burn_in must be >= 0, got {self.burn_in}")
        need(self.batch_windows >= 1, f"batch_windows must be >= 1, got {self.batch_windows}")
        need(self.demo_windows >= 0, f"demo_windows must be >= 0, got {self.demo_windows}")
        T = self.world_config().episode_steps
        need(self.unroll <= T, f"unroll ({self.unroll}) must be <= episode_steps ({T})")
        return self

    @property
    def batch_samples(self) -> int:
        return self.batch_windows

    def budget_note(self) -> str | None:
        """Why the exporter would refuse this actor (None when it fits the Kilobot)."""
        from export.codegen.budget import estimate
        from kiloforge.actors.base import HiddenArch
        from kiloforge.actors.registry import kind_named

        b = estimate(kind_named(self.cell), self.world_config(), HiddenArch(self.hidden))
        return None if b.ok else (f"an actor of {self.hidden} {self.cell.upper()} units does not fit the Kilobot "
                                  f"budget ({b.summary()})")

    @property
    def demo_samples(self) -> int:
        return self.demo_windows if self.demo_policy != "none" else 0


@dataclass
class ESConfig(ConfigBase):
    """Evolution strategies (learn.es): OpenAI-ES on the task's final success, from a behaviour-cloned MLP. Field docs double as --help."""

    algorithm: ClassVar[str] = "es"

    # --- task --------------------------------------------------------------------------------
    world: World = DEFAULT_WORLD  #: world preset (sim.config.PRESETS): kilobot (the robots') or thesis
    n_robots: Robots = (4, 16, 32)  #: swarm sizes; every generation plays each of them
    size_weights: tuple[int, ...] = ()  #: relative weight of each swarm size in the fitness (empty = equal)
    episode_steps: int = 0  #: control steps of a training episode; 0 = the world's (kilobot: 300)
    randomise: Randomise = "none"  #: domain randomisation of the training episodes (a name in sim.variants.RANDOMISATIONS)
    #: per swarm size, the randomisation of its training episodes (one name of sim.variants.RANDOMISATIONS per
    #: --robots entry); empty = --randomise for every size
    size_randomise: tuple[str, ...] = ()
    # --- actor (an MLP over the T_prev history, as MAGDDPG's) ---------------------------------
    t_prev: HistoryLength = 20  #: history length T_prev in (previous action, observation) tuples
    actor_hidden: tuple[int, ...] = (32, 32)  #: actor hidden widths (ELU); must fit the Kilobot to export
    # --- start: behaviour cloning of the demonstrator ------------------------------------------
    demo_policy: DemoPolicy = "searcher"  #: demonstrator: searcher or pusher (learn.demos), or none (random init)
    #: start from this MLP policy artifact (.npz: same world, t_prev and actor_hidden) instead of cloning; '' = clone
    init_policy: str = ""
    #: --demo-policy none: start from random weights whose output layer's bias is this value, so the first commands
    #: are near it (the actor's own start gives outputs near 0, clipped to [0, 1]: robots that stand still and a
    #: long plateau); 0 = the actor's own initialisation (docs/tasks.md)
    init_bias: float = 0.0
    demo_robot_episodes: int = 384  #: demonstrations per swarm size, in robot-episodes (episodes = this / robots)
    #: the demonstrator stops once its target is heard within this fraction of the range (0 = the searcher's tuned
    #: value, 0.6 in the kilobot world; 0.94 crowds 32 robots better, docs/results/localisation.md)
    demo_stop_dist: float = 0.0
    bc_updates: int = 6000  #: behaviour-cloning Adam steps
    bc_lr: float = 1e-3  #: Adam learning rate of behaviour cloning
    bc_batch: int = 2048  #: robot-steps per cloning step, split equally over the swarm sizes
    # --- evolution strategies -----------------------------------------------------------------
    generations: int = 60  #: ES generations (one update of the weights each)
    pairs: int = 16  #: antithetic pairs per generation (2 x pairs population members)
    sigma: float = 0.02  #: standard deviation of the weight perturbations
    lr: float = 0.01  #: Adam learning rate of the ES ascent
    episodes_per_member: int = 1  #: episodes per member and swarm size per generation (common to all members)
    #: per swarm size, episodes per member and generation (one count per --robots entry, e.g. 4 1 1: small swarms'
    #: fitness is the noisiest and the cheapest to average); empty = --episodes-per-member for every size
    size_episodes: tuple[int, ...] = ()
    # --- evaluation and bookkeeping ----------------------------------------------------------
    eval_every: int = 5  #: evaluate every this many generations (and after the last)
    eval_episodes: int = 16  #: deterministic evaluation episodes per swarm size (fixed seeds)
    eval_steps: int = BENCHMARK_STEPS  #: control steps of an evaluation episode (the thesis benchmark's 500)
    #: also keep every evaluated generation's weights as generations/gen_NNN.npz, to choose among them afterwards
    #: on other criteria (robustness variants, fresh episodes); changes nothing that is learned
    keep_evaluated: bool = False
    max_minutes: float = 0.0  #: stop after the first generation past this wall-clock time (0 = no limit)
    threads: int = 0  #: torch CPU threads (of the trainer and of each worker); 0 = auto (1)
    #: processes evaluating the population: 1 = this one (no Ray); N > 1 = N Ray workers of one CPU each, on a private
    #: local Ray or on the cluster of --ray-address (needs kiloforge[sweep]); the weights learned are the same for any N
    workers: int = 1
    ray_address: str = ""  #: join this Ray cluster (HOST:PORT or auto) instead of starting a local Ray; '' = local
    seed: int = 1  #: master seed (initial weights, demonstrations, cloning, perturbations, episodes, evaluation)
    exp_name: str = "es"  #: experiment name used in the default run directory name
    task: str = "localisation"  #: the task (sim.tasks): a built-in or plug-in name, or path/to/file.py:ClassName

    def validate(self) -> "ESConfig":
        """Raise :class:`ConfigError` (one line) for a bad value; return self."""
        need(self.world in WORLD_PRESETS, f"world must be one of {', '.join(sorted(WORLD_PRESETS))}, got '{self.world}'")
        self.check_task()
        need(len(self.n_robots) >= 1 and all(isinstance(m, int) and 1 <= m <= MAX_ROBOTS for m in self.n_robots),
             f"n_robots must be in 1..{MAX_ROBOTS}, got {_show(self.n_robots)}")
        need(len(set(self.n_robots)) == len(self.n_robots), f"n_robots lists a size twice: {_show(self.n_robots)}")
        need(not self.size_weights or (len(self.size_weights) == len(self.n_robots) and min(self.size_weights) >= 0
                                       and sum(self.size_weights) > 0),
             f"size_weights must be empty or one non-negative weight per swarm size ({len(self.n_robots)}), "
             f"got {list(self.size_weights)}")
        need(self.episode_steps >= 0, f"episode_steps must be >= 0 (0 = the world's), got {self.episode_steps}")
        need(1 <= self.t_prev <= 200, f"t_prev must be in 1..200, got {self.t_prev}")
        need(len(self.actor_hidden) >= 1 and all(1 <= w <= 4096 for w in self.actor_hidden),
             f"actor_hidden must be one or more widths in 1..4096, got {list(self.actor_hidden)}")
        need(self.demo_policy in DEMO_POLICIES,
             f"demo_policy must be one of {', '.join(DEMO_POLICIES)}, got '{self.demo_policy}'")
        need(0.0 <= self.demo_stop_dist <= 1.0, f"demo_stop_dist must be in [0, 1] (0 = tuned), got {self.demo_stop_dist}")
        for name in ("demo_robot_episodes", "bc_batch", "generations", "pairs", "episodes_per_member",
                     "eval_every", "eval_episodes", "eval_steps"):
            need(getattr(self, name) >= 1, f"{name} must be >= 1, got {getattr(self, name)}")
        need(self.bc_updates >= 0, f"bc_updates must be >= 0, got {self.bc_updates}")
        need(not self.init_policy or self.init_policy.endswith(".npz"),
             f"init_policy must be a policy artifact (.npz) or empty, got '{self.init_policy}'")
        need(math.isfinite(self.init_bias) and -1.0 <= self.init_bias <= 2.0,
             f"init_bias must be in [-1, 2] (0 = the actor's own initialisation), got {self.init_bias}")
        need(not self.init_bias or (self.demo_policy == "none" and not self.init_policy),
             "init_bias sets the output bias of a random start: give it with --demo-policy none and no --init-policy")
        for name in ("bc_lr", "sigma", "lr"):
            v = getattr(self, name)
            need(v > 0 and math.isfinite(v), f"{name} must be > 0, got {v}")
        need(self.max_minutes >= 0 and math.isfinite(self.max_minutes), f"max_minutes must be >= 0, got {self.max_minutes}")
        need(0 <= self.threads <= 256, f"threads must be in 0..256 (0 = auto), got {self.threads}")
        need(1 <= self.workers <= 4096, f"workers must be in 1..4096, got {self.workers}")
        need(self.ray_address == self.ray_address.strip() and "\n" not in self.ray_address,
             f"ray_address must be HOST:PORT, auto or empty, got {self.ray_address!r}")
        need(0 <= self.seed < 2 ** 63, f"seed must be a non-negative integer, got {self.seed}")
        need(re.fullmatch(r"[A-Za-z0-9._-]+", self.exp_name) is not None,
             f"exp_name may hold letters, digits, '-', '_' and '.', got '{self.exp_name}'")
        need(not self.size_randomise or len(self.size_randomise) == len(self.n_robots),
             f"size_randomise must be empty or one name per swarm size ({len(self.n_robots)}), "
             f"got {list(self.size_randomise)}")
        need(not self.size_randomise or self.randomise == "none",
             "give --randomise (every size) or --size-randomise (one per size), not both")
        for name in self.size_randomises():
            randomisation(name)  # ConfigError for an unknown name
        need(not self.size_episodes or (len(self.size_episodes) == len(self.n_robots) and min(self.size_episodes) >= 1),
             f"size_episodes must be empty or one count >= 1 per swarm size ({len(self.n_robots)}), "
             f"got {list(self.size_episodes)}")
        need(not self.size_episodes or self.episodes_per_member == 1,
             "give --episodes-per-member (every size) or --size-episodes (one per size), not both")
        need(self.eval_steps <= MAX_EPISODE_STEPS, f"eval_steps must be <= {MAX_EPISODE_STEPS}, got {self.eval_steps}")
        return self

    @property
    def total_episodes(self) -> int:
        """Training episodes of the whole run (every member, swarm size and generation)."""
        return self.generations * 2 * self.pairs * sum(self.size_episode_counts())

    def eval_world(self) -> WorldConfig:
        """The world of the evaluation episodes (the training world, its task's layout, with ``eval_steps`` steps)."""
        return self.task_spec().world(world_preset(self.world, episode_steps=self.eval_steps))

    def size_randomises(self) -> list[str]:
        """The randomisation name of each swarm size's training episodes."""
        return list(self.size_randomise) if self.size_randomise else [self.randomise] * len(self.n_robots)

    def size_episode_counts(self) -> list[int]:
        """Episodes per member and generation at each swarm size."""
        return list(self.size_episodes) if self.size_episodes else [self.episodes_per_member] * len(self.n_robots)

    def weights(self) -> list[float]:
        """The swarm sizes' fitness weights, summing to 1."""
        w = self.size_weights or (1,) * len(self.n_robots)
        return [x / sum(w) for x in w]

    def budget_note(self) -> str | None:
        """Why the exporter would refuse this actor (None when it fits the Kilobot)."""
        return TrainConfig(world=self.world, t_prev=self.t_prev, actor_hidden=self.actor_hidden).budget_note()


def randomisation(name: str) -> Any:
    """``sim.variants.RANDOMISATIONS[name]`` (None for ``none``); one-line ConfigError otherwise."""
    if name == "none":
        return None
    from sim.variants import RANDOMISATIONS  # looked up at each call (a test adds a randomisation of its own)

    if name not in RANDOMISATIONS:
        raise ConfigError(f"unknown randomise '{name}'; choose one of: {', '.join(dict.fromkeys(['none', *RANDOMISATIONS]))}")
    return RANDOMISATIONS[name]


def need(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _show(robots: tuple[int, ...]) -> str:
    return " ".join(map(str, robots)) if isinstance(robots, tuple) else repr(robots)


def _hints(cls: type) -> dict[str, Any]:
    """Field name -> type (Annotated unwrapped) of a config class."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        h = hints[f.name]
        out[f.name] = typing.get_args(h)[0] if typing.get_origin(h) is Annotated else h
    return out


def check_type(cls: type, name: str, value: Any) -> Any:
    """A JSON value as field ``name``'s type, exactly, by :mod:`kiloforge.validate`'s checks: integers for int
    fields (not booleans or 3.0), finite numbers for float fields, booleans for bool fields, strings for str
    fields, lists (``n_robots`` also a single integer) of integers for tuple fields. One-line ConfigError naming
    the field otherwise."""
    hint = _hints(cls)[name]
    try:
        if typing.get_origin(hint) is tuple:
            if name == "n_robots" and not isinstance(value, (list, tuple)):
                return (check_int(value, name),)
            if not isinstance(value, (list, tuple)):
                raise InputError(f"{name} must be a list of integers, got {show(value)}")
            return tuple(check_int(v, f"{name}[{i}]") for i, v in enumerate(value))
        if hint is float:
            return float(check_real(value, name))
        if hint is str:
            return check_str(value, name, MAX_TEXT_FIELD)
        return check_typed(value, hint.__name__, name)
    except InputError as e:
        raise ConfigError(str(e)) from None


def parse_text(cls: type, name: str, value: Any) -> Any:
    """Command-line text as field ``name``'s JSON value (then :func:`check_type` applies): a string for a
    scalar field, a string or list of strings of integers for a tuple field (``"32x32"``, ``["32", "32"]``;
    ``n_robots`` also a single integer). Values that are not text pass through unchanged."""
    hint = _hints(cls)[name]
    texts = value if isinstance(value, list) else [value]
    if not all(isinstance(v, str) for v in texts) or hint is str:
        return value

    def read(kind: str, conv):
        try:
            return conv(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: cannot read {value!r} as {kind}") from None

    if typing.get_origin(hint) is tuple:
        if name == "n_robots" and isinstance(value, str) and "x" not in value and " " not in value.strip():
            return read("int", int)
        items = value if isinstance(value, list) else value.replace("x", " ").split()
        return read("a list of integers", lambda _: [int(v) for v in items])
    if hint is int:
        return read("int", int)
    if hint is float:
        f = read("float", float)
        return f if math.isfinite(f) else read("a finite float", lambda _: float("x"))
    if hint is bool:
        return read("bool (true or false)", lambda v: {"true": True, "false": False}[v.strip().lower()])
    return value  # pragma: no cover


#: MAGDDPG training presets: fields that differ from TrainConfig's defaults. ``fast`` departs from the
#: thesis where wall clock on a small CPU matters (module doc, README); every value is overridable.
_FAST = {"n_envs": 16, "batch_size": 256, "tau": 0.005, "lr_critic": 1e-3, "lr_actor": 1e-3,
         "updates_per_step": 0.125, "warmup_episodes": 32, "episodes": 100_000, "replay_size": 200_000,
         "eval_every": 51_200, "eval_episodes": 50, "phantom_neighbours": 16.0, "exp_name": "fast"}
#: guidance by demonstrations: clone, a long critic-only phase, then small BC-anchored actor steps through
#: clip (not inverting) gradients: cloned commands sit at 0 and 1, where inverting gradients only push inwards
_GUIDED = {"demo_policy": "searcher", "bc_weight": 1000.0, "actor_delay": 20_000, "lr_actor": 3e-5,
           "noise_sigma": 0.1, "action_gradient": "clip"}
TRAIN_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "thesis": {"t_prev": 20},
    #: blocks of 8 steps' updates (1.4x the env steps/s: the updates no longer evict the env from the cache), the
    #: actor on every other update (TD3's delay) and, above 4 robots, its objective on 4 robots per sample with the
    #: others' replayed actions: 2.1x / 3.7x updates/s at 4 / 32 robots against 81d913c; the learning checks
    #: are in docs/speed.md. quick and guided keep every-step updates and the full actor objective, as measured.
    "fast": {**_FAST, "update_every": 8, "policy_every": 2, "actor_robots": 4, "actor_others": "replay"},
    #: a first policy in minutes: the searcher's clone, then RL anchored to it (kilobot world, 16 robots: 11x random, docs/training.md)
    "quick": {**_FAST, **_GUIDED, "demo_episodes": 128, "bc_updates": 1000, "replay_size": 100_000,
              "eval_every": 12_800, "max_minutes": 5.0, "exp_name": "quick"},
    "guided": {**_FAST, **_GUIDED, "exp_name": "guided"},
}
#: MAGRDPG training presets (RecurrentConfig's defaults are its ``fast``)
RECURRENT_PRESETS: dict[str, dict[str, Any]] = {
    "fast": {},
    "quick": {"max_minutes": 5.0, "replay_size": 100_000, "eval_every": 12_800, "exp_name": "gru-quick"},
    "guided": {**_GUIDED, "exp_name": "gru-guided"},
}
#: ES presets: ``default`` is the recipe of the shipped policy; ``quick`` a few minutes at 4 and 16 robots
ES_PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "quick": {"n_robots": [4, 16], "demo_robot_episodes": 192, "bc_updates": 2000, "generations": 12, "pairs": 8,
              "eval_every": 4, "eval_episodes": 8, "max_minutes": 8.0, "exp_name": "es-quick"},
}
PRESETS: dict[str, dict[str, dict[str, Any]]] = {"magddpg": TRAIN_PRESETS, "magrdpg": RECURRENT_PRESETS, "es": ES_PRESETS}


def from_preset(name: str, cls: type[ExperimentConfig] = TrainConfig, **overrides: Any) -> ExperimentConfig:
    """The training preset ``name`` of ``cls``'s algorithm with fields replaced (validated)."""
    presets = PRESETS[cls.algorithm]
    if name not in presets:
        raise ConfigError(f"unknown training preset '{name}'; choose one of: {', '.join(presets)}")
    return cls.from_dict({**presets[name], **overrides}).validate()
