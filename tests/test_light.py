"""The light field (sim.light), the graded light feature (sim, emulator, host C) and the phototaxis task (issue 43)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.errors import InputError
from sim.config import WorldConfig, preset
from sim.env import SwarmEnv
from sim.light import lamp_field, parse_lamps
from sim.tasks import get_task
from sim.tasks.phototaxis import spot_capacity
from sim.variants import robustness_suite
from tests.fixtures import synthetic_qpolicy

PHOTO = get_task("phototaxis")
WORLD = PHOTO.world(preset("kilobot"))
needs_gcc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def test_spot_and_gradient_values_at_known_points():
    """A soft-edged spot: peak inside, half at the nominal radius, 0 beyond the edge; a side lamp: peak to 0."""
    lamps = parse_lamps("spot:50,0,100,40,600;side:0,200", "t")
    pts = np.array([[[50, 0], [50 + 80, 0], [50, 100], [50, -120], [-250, 0], [250, 0]]], float)
    spot_only = lamp_field(pts, lamps[:1], 250.0)[0]
    np.testing.assert_allclose(spot_only, [600, 600, 300, 0, 0, 0])
    side = lamp_field(pts, lamps[1:], 250.0)[0]
    np.testing.assert_allclose(side[4:], [0, 200])  # far wall 0, the lamp's wall its peak
    np.testing.assert_allclose(lamp_field(pts, lamps, 250.0, brightness=np.array([0.5]))[0], 0.5 * (spot_only + side))


def test_legacy_world_reads_as_before_and_keeps_its_dict():
    """Without lamps or a sensor model the world dict has no new keys and the readings are floor / wall only."""
    loc = preset("kilobot")
    assert not loc.graded_light and not {"lamps", "light_noise", "light_gain_spread"} & set(loc.to_dict())
    env = SwarmEnv(loc, 2, 8, seed=1)
    _, info = env.reset()
    assert set(np.unique(info["light"])) <= {-1, loc.light_floor, loc.light_wall}
    assert WorldConfig.from_dict(WORLD.to_dict()) == WORLD and WORLD.to_dict()["lamps"] == WORLD.lamps


def test_readings_in_range_with_per_robot_gain_deterministic_per_seed():
    """Readings lie in 0..1023 or -1; gains and offsets are per robot, equal for equal seeds, differ otherwise."""
    w = dataclasses.replace(WORLD, light_gain_spread=0.3, light_offset_spread=40.0, light_dropout=0.2)
    a, b, c = (SwarmEnv(w, 2, 16, seed=s, task=PHOTO) for s in (5, 5, 6))
    la, lb, lc = (e.reset()[1]["light"] for e in (a, b, c))
    np.testing.assert_array_equal(la, lb)
    np.testing.assert_array_equal(a._sensors.gain, b._sensors.gain)
    assert not np.array_equal(a._sensors.gain, c._sensors.gain)
    assert np.unique(a._sensors.gain).size == 32 and np.unique(a._sensors.offset).size == 32
    assert la.min() >= -1 and la.max() <= 1023 and (la == -1).any()


def test_bad_lamps_are_one_line_errors():
    """An unknown lamp kind or a wrong count of numbers is refused naming the grammar."""
    for spec, msg in (("laser:1,2", "unknown lamp kind"), ("spot:1,2,3", "needs 5 finite numbers"),
                      ("spot:0,0,10,5,2000", "peak in 0..1023")):
        with pytest.raises(InputError, match=msg):
            dataclasses.replace(WORLD, lamps=spec)


def test_suite_gains_light_variants_only_with_lamps():
    """The suite adds lamp variants for worlds with lamps, a beacon variant only with a beacon; localisation's is unchanged."""
    names = set(robustness_suite(WORLD))
    assert {"lamps dimmer", "lamps brighter", "lamp shifted", "noisier light sensor"} <= names
    assert not any("lamp" in n or "light sensor" in n for n in robustness_suite(preset("kilobot")))
    assert "dim light" not in names and "dim light" in robustness_suite(preset("kilobot"))  # phototaxis: unlit walls
    assert "beacon pushed" not in names and "beacon pushed" in robustness_suite(preset("kilobot"))  # no beacon
    shifted = robustness_suite(WORLD)["lamp shifted"][0]
    assert shifted.lamp_list[0].x == 50.0


def test_light_feature_holds_the_last_valid_reading():
    """The sim's light feature: level = held / 1024, change 0 on a -1 reading and before any reading."""
    from sim.features import light_feature

    prev = np.array([[-1, 512, 512, 100]])
    light = np.array([[300, -1, 1023, 0]])
    f = light_feature(light, prev) * 1024
    np.testing.assert_array_equal(f[0], [[300, 0], [512, 0], [1023, 511], [0, -100]])


@needs_gcc
def test_light_block_equals_its_emulator_on_fuzzed_readings(tmp_path):
    """The light feature's C block (host build) equals the emulator byte for byte, readings incl. -1, 0, 1023."""
    world = dataclasses.replace(PHOTO.world(preset("kilobot", neighbour_table_size=5, period_ticks=12)),
                                obs_features="light,wall,rbf")  # both sensor features: one reading per step
    qp = synthetic_qpolicy(world, 3, (8,), seed=4)
    exe = build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], tmp_path, name="light")
    rng = np.random.default_rng(np.random.SeedSequence(43))
    inputs = random_inputs(rng, world.period_ticks, (), StreamSpec(n_robots=48, n_steps=60, rate=0.9),
                           fwspec.DEFAULT_MSG_TYPE, world.comm_radius_mm, world.light_threshold)
    pick = rng.random(inputs.light.shape)
    inputs.light[pick < 0.1] = 0
    inputs.light[(pick >= 0.1) & (pick < 0.2)] = 1023
    inputs.light[(pick >= 0.2) & (pick < 0.35)] = -1
    inputs.light[:5, :3] = -1  # no reading held yet
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib)
    want = emu.run(inputs)
    got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill="random:3")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    lvl = want.obs[..., world.obs_index("light")].astype(int)
    chg = want.obs[..., world.obs_index("light") + 1].astype(int)
    one = int(qp.one_q)
    assert lvl.max() == (1023 * one) >> 10 and (lvl[:5, :3] == 0).all() and (chg < 0).any() and (chg > 0).any()
    held = np.maximum.accumulate(np.where(inputs.light >= 0, np.arange(inputs.light.shape[1]), -1), axis=1)
    h = np.where(held >= 0, np.take_along_axis(inputs.light, np.maximum(held, 0), 1), 0)
    np.testing.assert_array_equal(lvl, (h.astype(int) * one) >> 10)  # the held reading's level, as specified


def test_spot_capacity_on_known_geometries():
    """One disc at radius 0; 3 at the circumradius of a triangle of side d; 7 at radius d (the optimum)."""
    assert spot_capacity(0.0, 33.0) == 1
    assert spot_capacity(33.0 / math.sqrt(3) + 1e-9, 33.0) == 3
    assert spot_capacity(33.0, 33.0) == 7
    assert PHOTO.ceiling(WORLD, 64) == min(64, spot_capacity(100.0, 33.0)) / 64


def test_phototaxis_world_per_size_has_the_anchor_spot_fraction():
    """16 and 32 robots: the 500 mm arena; 64: an arena whose area is the spot's / 6 %."""
    assert PHOTO.world_for(WORLD, 32) is WORLD and WORLD.arena_half_mm == 250.0
    big = PHOTO.world_for(WORLD, 64)
    assert math.pi * 100.0 ** 2 / (2 * big.arena_half_mm) ** 2 == pytest.approx(0.06, rel=0.01)


def test_sim_cli_runs_a_phototaxis_baseline(tmp_path, capsys):
    """python -m sim --task phototaxis --policy <a hand-written baseline or the shipped default> runs and reports the task's metric."""
    from kiloforge.sim_cli import main

    for policy in ("stop_in_light", "run_and_tumble", "default"):
        assert main(["--task", "phototaxis", "--policy", policy, "--robots", "6", "--episodes", "2", "--steps", "20",
                     "--out", str(tmp_path / policy), "--quiet"]) == 0
    assert "in spot" in capsys.readouterr().out


def test_export_of_a_phototaxis_policy_is_bit_exact_on_the_host(tmp_path, capsys):
    """python -m export --task phototaxis of a random-weights policy: the host build equals the emulator."""
    from export.cli.main import main
    from kiloforge.policies import save_policy
    from tests.fixtures import init_policy

    p = dataclasses.replace(init_policy(WORLD, 2, (8,)), task=PHOTO.ref)
    path = save_policy(p, tmp_path / "photo.npz")
    out = tmp_path / "photo.c"
    rc = main(["--task", "phototaxis", "--policy", str(path), "--out", str(out), "--verify", "host",
               "--robots-calib", "4", "--calib-steps", "20", "--no-avr", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and "bit-exact" in text
    assert "get_ambientlight()" in out.read_text() and "KF_OBS_LIGHT" in out.read_text()


def test_lamp_randomisation_draws_only_in_worlds_with_lamps():
    """--randomise table moves and dims the lamps per env in phototaxis (success follows the spot); localisation draws none."""
    from sim.variants import RANDOMISATIONS

    env = SwarmEnv(WORLD, 3, 8, seed=2, task=PHOTO, randomise=RANDOMISATIONS["table"])
    _, info = env.reset()
    d = env.world_draw
    assert d.lamp_shift_mm.shape == (3, 2) and d.lamp_brightness.shape == (3,) and d.light_noise.shape == (3,)
    centre = PHOTO.spot_centre(env)
    inside = np.hypot(*(env.pos - centre[:, None]).transpose(2, 0, 1)) <= 100.0
    np.testing.assert_array_equal(info["robot_success"], inside)
    loc = SwarmEnv(preset("kilobot"), 3, 8, seed=2, randomise=RANDOMISATIONS["table"])
    loc.reset()
    assert loc.world_draw.lamp_shift_mm is None and loc.world_draw.light_noise is None


def test_evaluate_runs_64_robots_in_the_anchor_arena():
    """learn evaluate asks the task for each size's world: phototaxis's 64 robots get the 724 mm arena."""
    from learn.evaluate import evaluate_policies
    from tests.fixtures import init_policy

    p = dataclasses.replace(init_policy(WORLD, 1, (4,)), task=PHOTO.ref)
    res = evaluate_policies({"mlp": p}, [4, 64], episodes=1, steps=3, out_dir=None, n_envs=1, gif=False,
                            progress=False, log=lambda s: None, task=PHOTO)
    assert "world" not in res["robots"]["4"] and res["robots"]["64"]["world"]["arena_half_mm"] == 362.0
    assert res["robots"]["64"]["metrics"]["mlp"]["summary"]["ceiling"]["mean"] == pytest.approx(37 / 64)


def test_fast_observe_equals_events_path_for_phototaxis():
    """The light feature (noise, gains, dropout): the fast observation equals sim.events.observe bit for bit."""
    w = dataclasses.replace(PHOTO.world(preset("kilobot", arena_half_mm=150.0)), light_dropout=0.3)
    fast = SwarmEnv(w, 2, 12, seed=9, task=PHOTO)
    slow = SwarmEnv(w, 2, 12, seed=9, task=PHOTO, fast_observe=False)
    o1, o2 = fast.reset()[0], slow.reset()[0]
    rng = np.random.default_rng(0)
    changed = False
    for _ in range(6):
        np.testing.assert_array_equal(o1, o2)
        changed |= bool((o1[..., w.obs_index("light") + 1] != 0).any())
        a = rng.random((2, 12, 2))
        o1, o2 = fast.step(a)[0], slow.step(a)[0]
    assert changed


def test_trainers_play_each_swarm_size_in_the_tasks_world_for_it():
    """ES fitness, evaluators and training groups of phototaxis at 64 robots run in world_for's larger arena."""
    torch = pytest.importorskip("torch")
    from learn.es import PopulationMLP, rollout_population
    from learn.es_pool import child
    from learn.es_train import TaskFitness
    from learn.evaluate import Evaluator
    from learn.groups import make_env
    from learn.networks import Actor

    world = dataclasses.replace(WORLD, episode_steps=3)
    big = PHOTO.world_for(world, 64)
    assert big.arena_half_mm > world.arena_half_mm
    assert make_env(world, 1, 64, 0, task=PHOTO).cfg == big and make_env(world, 1, 16, 0, task=PHOTO).cfg == world
    assert Evaluator(world, 64, 1, 0, task=PHOTO).env.cfg == big
    torch.manual_seed(0)
    actor = Actor(world.history_dim(2), (4,))
    pop = PopulationMLP.of(actor.net)
    theta = torch.nn.utils.parameters_to_vector(actor.net.parameters()).detach()[None]
    ss = np.random.SeedSequence(3)
    got = TaskFitness("phototaxis", pop, world, 2, (64,), (None,), (4,))(theta, 0, ss)
    seeds = [child(ss, 1, e) for e in range(4)]
    want = rollout_population(pop, theta, big, 64, seeds, 2, None, PHOTO).final_success.mean(axis=1)
    small = rollout_population(pop, theta, world, 64, seeds, 2, None, PHOTO).final_success.mean(axis=1)
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, small)
