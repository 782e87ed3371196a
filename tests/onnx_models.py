"""A tiny ONNX MLP actor for tests that need a model file (Gemm -> Relu -> Gemm on the thesis world, t_prev 1)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.config import preset

T_PREV = 1


def tiny_model(path: Path, metadata: bool = True, world_meta: str | None = None, seed: int = 5) -> Path:
    """Write the model to ``path``. Its kiloforge metadata holds the thesis world (``metadata``), this world
    JSON text (``world_meta``), or nothing (then the world must come from a world JSON)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    world = preset("thesis")
    d = world.history_dim(T_PREV)
    rng = np.random.default_rng(np.random.SeedSequence([55, seed]))
    inits = [numpy_helper.from_array(rng.normal(0, 0.3, (8, d)).astype(np.float32), "w1"),
             numpy_helper.from_array(np.zeros(8, np.float32), "b1"),
             numpy_helper.from_array(rng.normal(0, 0.5, (2, 8)).astype(np.float32), "w2"),
             numpy_helper.from_array(np.full(2, 0.5, np.float32), "b2")]
    nodes = [helper.make_node("Gemm", ["x", "w1", "b1"], ["z1"], transB=1), helper.make_node("Relu", ["z1"], ["a1"]),
             helper.make_node("Gemm", ["a1", "w2", "b2"], ["y"], transB=1)]
    g = helper.make_graph(nodes, "actor", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", d])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 2])], initializer=inits)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    if world_meta is not None or metadata:
        helper.set_model_props(m, {"kiloforge.world": world.to_json() if world_meta is None else world_meta,
                                   "kiloforge.t_prev": str(T_PREV)})
    onnx.save(m, str(path))
    return path
