"""Deterministic policies for tests and benchmarks (no training): float MLPs with the thesis's
initialisation and synthetic int8 MLPs that exercise every integer path of the firmware.

A trained policy is not needed to check that the generated C, its emulator and the AVR build agree
bit for bit: what matters is that every integer path is exercised. :func:`synthetic_qpolicy` draws
int8 weights from a seeded generator and picks biases and shifts so that hidden pre-activations
spread over the whole int8 range (some saturate) and the motor commands over 0..255.
"""
from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np

from kiloforge import numfmt
from kiloforge.actors.base import sensing_tables
from kiloforge.actors.mlp import MLPPolicy, QuantizedMLP
from kiloforge.numfmt import QuantLayer
from sim.config import ACTION_DIM, WorldConfig
from sim.tasks import DEFAULT_TASK, get_task

#: the emitter's own program as the default task (localisation) writes it (the beacon's kilobot_target.c)
TARGET_FILE = get_task(DEFAULT_TASK).emitter_program
TABLE_EXPONENTS = (5, 6)  #: (e_z, e_a) of synthetic table activations
FLASH_HEADROOM_B = 1_500  #: flash the shipped default policy leaves free for error in the code estimate


def init_policy(world: WorldConfig, t_prev: int, hidden: Sequence[int], activation: str = "elu",
                seed: int = 0, out_scale: float = 3e-3, provenance: dict | None = None) -> MLPPolicy:
    """A randomly initialised MLP actor (thesis §4.3.1): U[±1/sqrt(f)] hidden, U[±out_scale] output."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    sizes = [world.history_dim(t_prev), *hidden, 2]
    ws, bs = [], []
    for k in range(len(sizes) - 1):
        f = sizes[k]
        lim = out_scale if k == len(sizes) - 2 else 1.0 / np.sqrt(f)
        ws.append(rng.uniform(-lim, lim, size=(sizes[k + 1], f)).astype(np.float32))
        bs.append(rng.uniform(-lim, lim, size=(sizes[k + 1],)).astype(np.float32))
    acts = [activation] * len(hidden) + ["identity"]
    return MLPPolicy(weights=ws, biases=bs, activations=acts, t_prev=t_prev, world=world,
                     provenance=dict(provenance or {}))


def synthetic_qpolicy(world: WorldConfig, t_prev: int, hidden: Sequence[int] = (8,),
                      activations: Sequence[str] | None = None, seed: int = 0, e_in: int = 6) -> QuantizedMLP:
    """A QuantizedMLP with random int8 weights; same arguments, same policy (and same hash).

    ``activations``: one per hidden layer (default ReLU), any of numfmt.ACTIVATIONS.
    """
    acts = list(activations) if activations is not None else ["relu"] * len(hidden)
    assert len(acts) == len(hidden), f"{len(acts)} activations for {len(hidden)} hidden layers"
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    sizes = [world.history_dim(t_prev), *map(int, hidden), ACTION_DIM]
    x_probe = rng.integers(-64, 65, size=(256, sizes[0]))  # typical input magnitudes
    layers: list[QuantLayer] = []
    e_prev = e_in
    for k in range(len(sizes) - 1):
        n_in, n_out = sizes[k], sizes[k + 1]
        last = k == len(sizes) - 2
        w = rng.integers(-127, 128, size=(n_out, n_in))
        w[rng.random((n_out, n_in)) < 0.25] = 0  # some sparsity, like trained nets after quantisation
        w = w.astype(np.int8)
        acc = x_probe @ w.T.astype(np.int64)  # (256, n_out)
        spread = np.maximum(acc.std(axis=0), 1.0)
        target = 60.0 if last else 48.0  # requantised standard deviation
        shift = np.clip(np.round(np.log2(spread / target)) + rng.integers(-1, 2, n_out), 0, numfmt.MAX_SHIFT)
        shift = shift.astype(np.uint8)
        b = np.round(rng.normal(0.0, 0.5, n_out) * spread).astype(np.int64)
        if last:
            b += np.left_shift(np.int64(128), shift.astype(np.int64))  # centre the commands near 128
            lo, hi, act, e_out, e_act, table = 0, 255, "identity", 0, 0, None
        else:
            lo, hi, act = numfmt.INT8_MIN, numfmt.INT8_MAX, acts[k]
            if act in numfmt.TABLE_ACTIVATIONS:
                e_out, e_act = TABLE_EXPONENTS
                table = numfmt.act_table(act, e_out, e_act)
            else:
                e_out = e_act = 4
                table = None
        layer = QuantLayer(w=w, b=b.astype(np.int32), shift=shift, lo=lo, hi=hi, activation=act, e_in=e_prev,
                           e_out=e_out, e_act=e_act, table=table)
        layers.append(layer)
        x_probe = np.clip(layer.forward(x_probe), -128, 127)
        e_prev = e_act
    digest = hashlib.sha256()
    for layer in layers:
        for arr in (layer.w, layer.b, layer.shift):
            digest.update(np.ascontiguousarray(arr).tobytes())
    digest.update(world.to_json().encode())
    return QuantizedMLP(layers=layers, e_in=e_in, world=world, t_prev=t_prev, policy_hash=digest.hexdigest(),
                        **sensing_tables(world, e_in))


def random_sequences(world: WorldConfig, n_seq: int, steps: int, seed: int) -> np.ndarray:
    """Input tuples shaped like real ones: actions in [0, 1], flags, target -1 or [0, 1], RBF bins."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    x = np.empty((n_seq, steps, world.tuple_dim), np.float32)
    x[..., :2] = rng.random((n_seq, steps, 2))
    x[..., 2] = rng.random((n_seq, steps)) < 0.1
    x[..., 3] = np.where(rng.random((n_seq, steps)) < 0.3, rng.random((n_seq, steps)), -1.0)
    x[..., 4] = rng.random((n_seq, steps)) < 0.2
    x[..., 5:] = rng.exponential(0.2, (n_seq, steps, world.n_rbf))
    return x
