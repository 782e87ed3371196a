"""Evolution strategies: the batched population MLP, common random numbers, ranks, the run and its exact resume."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from kiloforge.policies import load_policy  # noqa: E402
from learn.__main__ import main  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.config import ConfigError, ESConfig, from_preset  # noqa: E402
from learn.es import Adam, PopulationMLP, centred_ranks, es_direction, rollout_population  # noqa: E402
from learn.es_train import train_es  # noqa: E402
from learn.networks import Actor  # noqa: E402
from tests.signal_delivery import deliver  # noqa: E402
from sim.config import preset  # noqa: E402
from sim.env import SwarmEnv  # noqa: E402
from sim.history import History  # noqa: E402
from sim.metrics import final_success  # noqa: E402

#: a run of a few seconds
TINY = dict(n_robots=(2, 3), t_prev=2, actor_hidden=(8,), episode_steps=20, demo_robot_episodes=6, bc_updates=20,
            bc_batch=64, generations=4, pairs=2, eval_every=2, eval_episodes=2, eval_steps=30, threads=1)


def _quiet(_msg: str) -> None:
    pass


def test_population_mlp_matches_the_actor():
    """Member k of PopulationMLP computes exactly what the actor's nn.Sequential does with θ_k."""
    torch.manual_seed(0)
    actors = [Actor(12, (7, 5)) for _ in range(3)]
    pop = PopulationMLP.of(actors[0].net)
    theta = torch.stack([torch.nn.utils.parameters_to_vector(a.net.parameters()).detach() for a in actors])
    assert theta.shape == (3, pop.n_params)
    x = torch.randn(3, 11, 12)
    got = pop.forward(theta, x)
    want = torch.stack([a.net(x[k]) for k, a in enumerate(actors)]).detach()
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


def test_population_members_meet_the_same_episodes():
    """Common random numbers: every member plays episode e from its seed; member k equals a single-env run."""
    world = preset("kilobot", episode_steps=25)
    torch.manual_seed(1)
    actor = Actor(world.history_dim(2), (8,))
    pop = PopulationMLP.of(actor.net)
    base = torch.nn.utils.parameters_to_vector(actor.net.parameters()).detach().double()
    theta = torch.stack([base, base, base + 0.3 * torch.randn_like(base)])
    seeds = [np.random.SeedSequence(5, spawn_key=(e,)) for e in range(2)]
    res = rollout_population(pop, theta, world, 3, seeds, 2)
    assert res.final_success.shape == (3, 2)
    np.testing.assert_array_equal(res.final_success[0], res.final_success[1])
    np.testing.assert_array_equal(res.returns[0], res.returns[1])
    # member 2, episode 1, alone
    env = SwarmEnv(world, n_envs=1, n_robots=3, seed=[seeds[1]])
    obs, _ = env.reset()
    hist = History(2, world.obs_dim)
    h = hist.reset(obs)
    cov = np.zeros((1, world.episode_steps))
    ret = 0.0
    for t in range(world.episode_steps):
        a = pop.forward(theta[2:3].float(), torch.from_numpy(h).reshape(1, 3, -1)).clamp(0, 1).reshape(1, 3, -1)
        obs, r, _, _, info = env.step(a.numpy().astype(np.float64))
        cov[:, t] = info["coverage"]
        ret += r[0]
        h = hist.push(a.numpy(), obs)
    assert final_success(cov)[0] == res.final_success[2, 1]
    assert ret == pytest.approx(res.returns[2, 1], rel=1e-12)


def test_centred_ranks_and_direction():
    """Ranks lie in [-0.5, 0.5] with ties averaged; the direction weights each ε by its pair's difference."""
    np.testing.assert_array_equal(centred_ranks(np.array([3.0, 1.0, 2.0])), [0.5, -0.5, 0.0])
    np.testing.assert_array_equal(centred_ranks(np.array([1.0, 1.0, 0.0, 2.0])), [0.0, 0.0, -0.5, 0.5])
    assert centred_ranks(np.array([4.0])).tolist() == [0.0]
    eps = torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=torch.float64)
    g = es_direction(np.array([0.5, 0.0, -0.5, 0.0]), eps, sigma=0.5)  # pair 0 better at +ε, pair 1 even
    torch.testing.assert_close(g, torch.tensor([0.5, 0.0], dtype=torch.float64))  # (0.5 + 0.5) ε_0 / (2·2·0.5)


def test_adam_state_round_trip():
    """Adam continued from its state dict steps exactly like the uninterrupted one."""
    a, b = Adam(3, 0.1), Adam(3, 0.1)
    th = torch.zeros(3, dtype=torch.float64)
    g = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    ta = a.step(a.step(th, g), g)
    tb = b.step(th, g)
    c = Adam(3, 0.1)
    c.load_state_dict(b.state_dict())
    assert torch.equal(ta, c.step(tb, g))


def test_es_run_resumes_exactly_and_exports(tmp_path):
    """A run stopped at generation 2 and resumed ends with the same weights as one run straight to 4; policies export."""
    cfg = ESConfig(**TINY, seed=2)
    full = train_es(cfg, tmp_path / "full", progress=False, log=_quiet)
    assert full.stopped == "done" and full.counters.rows[-1]["generation"] == 4
    part = train_es(ESConfig(**{**TINY, "generations": 2}, seed=2), tmp_path / "part", progress=False, log=_quiet)
    assert part.counters.rows[-1]["generation"] == 2
    assert main(["train-es", "--out", str(tmp_path / "part"), "--resume", "--generations", "4", "--quiet"]) == 0
    a = load_checkpoint(tmp_path / "full" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "part" / "checkpoint.pt")
    assert a["es_generation"] == b["es_generation"] == 4
    assert torch.equal(a["theta"], b["theta"])
    other = train_es(ESConfig(**TINY, seed=3), tmp_path / "other", progress=False, log=_quiet)
    assert not torch.equal(a["theta"], load_checkpoint(other.run_dir / "checkpoint.pt")["theta"])
    for name in ("policy_bc.npz", "policy_best.npz", "policy_last.npz"):
        pol = load_policy(tmp_path / "full" / name)
        assert pol.t_prev == 2
    from export.__main__ import main as export_main

    out = tmp_path / "p.c"
    assert export_main(["--policy", str(tmp_path / "full" / "policy_best.npz"), "--out", str(out)]) == 0
    assert "loop" in out.read_text()


def test_keep_evaluated_keeps_every_evaluated_generation(tmp_path):
    """keep_evaluated writes one policy per evaluation (the last equals policy_last.npz) and learns the same weights."""
    kept = train_es(ESConfig(**TINY, seed=2, keep_evaluated=True), tmp_path / "kept", progress=False, log=_quiet)
    plain = train_es(ESConfig(**TINY, seed=2), tmp_path / "plain", progress=False, log=_quiet)
    names = sorted(p.name for p in (kept.run_dir / "generations").iterdir())
    assert names == ["gen_000.npz", "gen_002.npz", "gen_004.npz"]
    assert not (plain.run_dir / "generations").exists()
    last, gen4 = load_policy(kept.run_dir / "policy_last.npz"), load_policy(kept.run_dir / "generations" / "gen_004.npz")
    assert all(np.array_equal(a, b) for a, b in zip(last.weights, gen4.weights))
    assert gen4.provenance["generations"] == 4
    assert torch.equal(load_checkpoint(kept.run_dir / "checkpoint.pt")["theta"],
                       load_checkpoint(plain.run_dir / "checkpoint.pt")["theta"])


def test_size_randomise_draws_each_sizes_own_randomisation(tmp_path, monkeypatch):
    """--size-randomise gives each swarm size its own randomisation; the same name everywhere is --randomise."""
    import learn.es_train as es_train
    from sim.variants import RANDOMISATIONS

    seen = []

    def spy(pop, members, world, M, seeds, t_prev, randomise=None, task=None):
        seen.append((M, randomise))
        return rollout_population(pop, members, world, M, seeds, t_prev, randomise, task)

    monkeypatch.setattr(es_train, "rollout_population", spy)
    train_es(ESConfig(**TINY, size_randomise=("none", "table-free-beacon")), tmp_path / "mixed", progress=False,
             log=_quiet)
    assert set(seen) == {(2, None), (3, RANDOMISATIONS["table-free-beacon"])}
    same = train_es(ESConfig(**TINY, size_randomise=("table", "table")), tmp_path / "same", progress=False, log=_quiet)
    plain = train_es(ESConfig(**TINY, randomise="table"), tmp_path / "plain", progress=False, log=_quiet)
    theta = {r.run_dir.name: load_checkpoint(r.run_dir / "checkpoint.pt")["theta"] for r in (same, plain)}
    assert torch.equal(theta["same"], theta["plain"])


def test_size_episodes_give_each_size_its_own_episode_count(tmp_path, monkeypatch):
    """--size-episodes plays each swarm size its own number of episodes; the same count everywhere is
    --episodes-per-member."""
    import learn.es_train as es_train

    seen = []

    def spy(pop, members, world, M, seeds, t_prev, randomise=None, task=None):
        seen.append((M, len(seeds)))
        return rollout_population(pop, members, world, M, seeds, t_prev, randomise, task)

    monkeypatch.setattr(es_train, "rollout_population", spy)
    mixed = train_es(ESConfig(**TINY, size_episodes=(3, 1)), tmp_path / "mixed", progress=False, log=_quiet)
    assert set(seen) == {(2, 3), (3, 1)}
    assert mixed.counters.episodes == TINY["generations"] * 2 * TINY["pairs"] * (3 + 1)
    same = train_es(ESConfig(**TINY, size_episodes=(2, 2)), tmp_path / "same", progress=False, log=_quiet)
    plain = train_es(ESConfig(**TINY, episodes_per_member=2), tmp_path / "plain", progress=False, log=_quiet)
    theta = {r.run_dir.name: load_checkpoint(r.run_dir / "checkpoint.pt")["theta"] for r in (same, plain)}
    assert torch.equal(theta["same"], theta["plain"])


def test_es_config_errors():
    """Bad ES fields are one-line ConfigErrors; the presets validate."""
    for preset_name in ("default", "quick"):
        from_preset(preset_name, ESConfig)
    with pytest.raises(ConfigError, match="size_weights"):
        ESConfig(n_robots=(4, 16), size_weights=(1,)).validate()
    with pytest.raises(ConfigError, match="sigma"):
        ESConfig(sigma=0).validate()
    with pytest.raises(ConfigError, match="size_randomise"):
        ESConfig(n_robots=(4, 16), size_randomise=("table",)).validate()
    with pytest.raises(ConfigError, match="not both"):
        ESConfig(n_robots=(4, 16), randomise="table", size_randomise=("table", "none")).validate()
    with pytest.raises(ConfigError, match="size_episodes"):
        ESConfig(n_robots=(4, 16), size_episodes=(2, 0)).validate()
    with pytest.raises(ConfigError, match="not both"):
        ESConfig(n_robots=(4, 16), episodes_per_member=2, size_episodes=(2, 1)).validate()
    with pytest.raises(ConfigError, match="unknown randomise 'tabel'"):
        ESConfig(n_robots=(4, 16), size_randomise=("table", "tabel")).validate()
    with pytest.raises(ConfigError, match="es config, not magddpg|this is a"):
        from learn.config import TrainConfig

        TrainConfig.from_dict({"algorithm": "es"})


def test_es_cli_refuses_bad_flags(tmp_path, capsys):
    """A bad flag is one line on stderr and exit status 2, with nothing written."""
    assert main(["train-es", "--pairs", "0", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pairs" in err[0]
    assert not (tmp_path / "r").exists()


def test_sigint_mid_generation_checkpoints_and_resumes_exactly(tmp_path, monkeypatch):
    """SIGINT inside a generation abandons it, checkpoints the last finished one (exit 130); resuming ends where an
    uninterrupted run does."""
    import signal

    import learn.es_train as et

    cfg = ESConfig(**TINY, seed=4)
    full = train_es(cfg, tmp_path / "full", progress=False, log=_quiet)
    real, calls = et.rollout_population, []

    def interrupting(*a, **k):
        calls.append(1)
        if len(calls) == 5:  # generation 3, first swarm size
            deliver(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(et, "rollout_population", interrupting)
    cut = train_es(cfg, tmp_path / "cut", progress=False, log=_quiet)
    monkeypatch.setattr(et, "rollout_population", real)
    assert cut.stopped == "interrupted" and cut.exit_status == 130
    assert load_checkpoint(tmp_path / "cut" / "checkpoint.pt")["es_generation"] == 2
    train_es(cfg, tmp_path / "cut", resume=True, progress=False, log=_quiet)
    a = load_checkpoint(full.run_dir / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "cut" / "checkpoint.pt")
    assert a["es_generation"] == b["es_generation"] == 4 and torch.equal(a["theta"], b["theta"])
    assert a["counters"]["env_steps"] == b["counters"]["env_steps"]


def test_es_time_budget_bar_in_a_log(tmp_path, capsys):
    """With max_minutes the ES bar measures the time budget too, shows generations as x/total, and writes no \\r."""
    train_es(ESConfig(**TINY, seed=2, max_minutes=10.0), tmp_path / "run", progress=True, log=_quiet)
    err = capsys.readouterr().err
    assert "\r" not in err and "\x1b" not in err
    lines = [line for line in err.splitlines() if line.startswith("run:")]
    assert lines and all("<" in line for line in lines)  # elapsed<remaining of the budget bar
    assert "4/4 gen" in lines[-1], lines[-1]


def test_init_policy_starts_from_the_artifact(tmp_path):
    """--init-policy starts the ascent from the artifact's exact weights (no cloning), records its hash, and
    refuses an artifact of another shape with one line."""
    from learn.es_train import actor_algo, init_policy_of, load_weights

    src = train_es(ESConfig(**TINY, seed=4), tmp_path / "src", progress=False, log=_quiet)
    start = tmp_path / "src" / "policy_last.npz"
    want = load_policy(start)
    cfg = ESConfig(**{**TINY, "generations": 1}, seed=4, init_policy=str(start))
    algo = actor_algo(cfg, cfg.world_config())
    load_weights(algo, init_policy_of(cfg, algo, cfg.world_config()))
    got = algo.artifact(cfg.world_config(), {})
    for a, b in zip(got.weights + got.biases, want.weights + want.biases):
        np.testing.assert_array_equal(a, b)
    ft = train_es(cfg, tmp_path / "ft", progress=False, log=_quiet)
    assert not (tmp_path / "ft" / "policy_bc.npz").exists()
    # same seed, same evaluation episodes: generation 0 of the new run is the source's last evaluation
    assert ft.counters.rows[0]["eval_final_coverage"] == src.counters.rows[-1]["eval_final_coverage"]
    assert load_policy(tmp_path / "ft" / "policy_last.npz").provenance["init_policy_hash"] == want.hash
    with pytest.raises(ConfigError, match="differs from this run in .*layers"):
        train_es(ESConfig(**{**TINY, "actor_hidden": (6,)}, init_policy=str(start)), tmp_path / "bad",
                 progress=False, log=_quiet)
    assert not (tmp_path / "bad").exists()
    with pytest.raises(ConfigError, match="init_policy must be"):
        ESConfig(init_policy="x.pt").validate()


def test_init_policy_may_train_with_another_episode_length(tmp_path):
    """--init-policy accepts an artifact trained with other training-episode steps (same world otherwise)
    and refuses one of another world with one line."""
    from learn.es_train import actor_algo, init_policy_of

    train_es(ESConfig(**TINY, seed=4), tmp_path / "src", progress=False, log=_quiet)
    start = str(tmp_path / "src" / "policy_last.npz")
    longer = ESConfig(**{**TINY, "episode_steps": 2 * TINY["episode_steps"]}, init_policy=start)
    algo = actor_algo(longer, longer.world_config())
    assert init_policy_of(longer, algo, longer.world_config()).hash == load_policy(start).hash
    other = ESConfig(**{**TINY, "world": "thesis"}, init_policy=start)
    with pytest.raises(ConfigError, match="differs from this run in world"):
        init_policy_of(other, actor_algo(other, other.world_config()), other.world_config())


def test_init_bias_starts_random_weights_with_that_output_bias(tmp_path):
    """--init-bias: a random start (no cloning) whose output biases are the value after one Adam step at most
    lr away; the other layers are the plain random start's; refused with a demonstrator or an init policy."""
    kw = {**TINY, "demo_policy": "none", "generations": 1, "seed": 5}
    lines: list[str] = []
    train_es(ESConfig(**kw, init_bias=0.5), tmp_path / "b", progress=False, log=lines.append)
    train_es(ESConfig(**kw), tmp_path / "plain", progress=False, log=_quiet)
    assert any("output bias at 0.5" in line for line in lines) and not (tmp_path / "b" / "policy_bc.npz").exists()
    b, plain = load_policy(tmp_path / "b" / "policy_last.npz"), load_policy(tmp_path / "plain" / "policy_last.npz")
    lr = ESConfig().lr
    assert np.all(np.abs(np.asarray(b.biases[-1]) - 0.5) <= 1.01 * lr)
    assert np.all(np.abs(np.asarray(plain.biases[-1]) - 0.5) > 0.1)
    for x, y in zip(b.weights[:-1], plain.weights[:-1]):  # same draw; one Adam step apart at most
        assert np.max(np.abs(np.asarray(x) - np.asarray(y))) <= 2.02 * lr
    with pytest.raises(ConfigError, match="init_bias sets the output bias of a random start"):
        ESConfig(demo_policy="searcher", init_bias=0.5).validate()
    with pytest.raises(ConfigError, match="init_bias must be in"):
        ESConfig(demo_policy="none", init_bias=float("inf")).validate()
