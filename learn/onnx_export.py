"""ONNX out: the float actor (a torch MLP or a policy artifact) → an ``.onnx`` file any runtime can run.

The graph is written directly with ``onnx.helper`` from the layer weights (no ``torch.onnx``: a torch
actor and its ``.npz`` artifact give the same graph and the same float32 weights, deterministically,
and neither onnxscript nor the deprecated TorchScript exporter is needed)::

    history  float32 [N, t_prev * (2 + obs_dim)]   oldest tuple first, each [a_prev_l, a_prev_r, obs...]
      → Gemm(transB=1) → Elu → ... → Gemm(transB=1) → Clip(0, 1)
    action   float32 [N, 2]                         (u_left, u_right) in [0, 1]

``metadata_props`` carry everything needed to bring the file back to a Kilobot
(:func:`export.interop.onnx_import.load_onnx_policy`): ``kiloforge.world`` (WorldConfig JSON),
``kiloforge.t_prev``, ``kiloforge.obs_layout`` (feature names of one tuple, oldest-first order),
``kiloforge.action`` (``clip01``), ``kiloforge.version``, ``kiloforge.policy_hash``,
``kiloforge.activations``. Default opset: 17 (``DEFAULT_OPSET``).

CLI: ``python -m learn.onnx_export --policy P.npz --out actor.onnx`` (also
:func:`main_export_onnx` for ``python -m learn export-onnx``).
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any, Sequence

import numpy as np

from export.interop.onnx_import import META_ACTION, META_OBS_LAYOUT, META_T_PREV, META_VERSION, META_WORLD
from kiloforge.errors import KiloforgeError
from kiloforge.io import write_atomic
from kiloforge.numfmt import ACTIVATIONS, act_float
from kiloforge.policies import load_policy
from kiloforge.validate import int_arg
from sim.config import ACTION_DIM, WorldConfig
from sim.features import input_names

DEFAULT_OPSET = 17
MIN_OPSET = 11  #: Clip takes its bounds as inputs from opset 11
INPUT_NAME = "history"
OUTPUT_NAME = "action"
_ONNX_ACT = {"elu": "Elu", "relu": "Relu", "tanh": "Tanh", "sigmoid": "Sigmoid"}


class OnnxExportError(KiloforgeError):
    """The actor cannot be written as a kiloforge ONNX model; the message is one line."""


def kiloforge_version() -> str:
    """kiloforge's version, written into the model's metadata."""
    from kiloforge import __version__

    return __version__


def obs_layout(world: WorldConfig) -> dict[str, Any]:
    """Names of one history tuple's features, in input order (the world's layout, sim.features)."""
    names = input_names(world)
    return {"tuple": ["a_prev_left", "a_prev_right"] + names, "tuple_dim": world.tuple_dim,
            "order": "oldest tuple first", "action": ["u_left", "u_right"]}


# --- getting (W, b, activation) layers out of whatever we were given ----------------------------
def _layers_from_sequential(seq: Any) -> list[tuple[np.ndarray, np.ndarray, str]]:
    from torch import nn

    mods: list[nn.Module] = []

    def flatten(m: nn.Module) -> None:
        for c in m:
            flatten(c) if isinstance(c, nn.Sequential) else mods.append(c)

    flatten(seq)
    acts = {nn.ELU: "elu", nn.ReLU: "relu", nn.Tanh: "tanh", nn.Sigmoid: "sigmoid"}
    layers: list[list[Any]] = []
    for m in mods:
        if isinstance(m, nn.Linear):
            if layers and layers[-1][2] is None:
                layers[-1][2] = "identity"
            b = m.bias.detach().cpu().numpy() if m.bias is not None else np.zeros(m.out_features)
            layers.append([m.weight.detach().cpu().numpy().astype(np.float32).copy(), b.astype(np.float32).copy(), None])
        elif type(m) in acts:
            if isinstance(m, nn.ELU) and float(m.alpha) != 1.0:
                raise OnnxExportError(f"ELU(alpha={m.alpha:g}) is not supported (the firmware's ELU has alpha 1)")
            if not layers or layers[-1][2] is not None:
                raise OnnxExportError(f"{type(m).__name__} must follow a Linear layer (one activation per layer)")
            layers[-1][2] = acts[type(m)]
        elif isinstance(m, (nn.Identity, nn.Dropout, nn.Flatten)):
            continue
        else:
            raise OnnxExportError(f"module {type(m).__name__} is not supported: the actor must be a Sequential of "
                                  "Linear / ELU / ReLU / Tanh / Sigmoid")
    if not layers:
        raise OnnxExportError("the module has no Linear layer")
    for l in layers:
        l[2] = l[2] or "identity"
    return [tuple(l) for l in layers]  # type: ignore[misc]


def _layers_from_module(module: Any) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """A learn.networks.Actor (its ``layers()``), an nn.Sequential, or a module holding one Sequential."""
    from torch import nn

    lay = getattr(module, "layers", None)
    if callable(lay) and not isinstance(lay, nn.Module) and not isinstance(module, nn.Sequential):
        return [(np.asarray(w, np.float32), np.asarray(b, np.float32), str(a)) for w, b, a in module.layers()]
    if isinstance(module, nn.Sequential):
        return _layers_from_sequential(module)
    seqs = [m for m in module.children() if isinstance(m, nn.Sequential)]
    if len(seqs) == 1:
        return _layers_from_sequential(seqs[0])
    if isinstance(module, nn.Linear):
        return _layers_from_sequential(nn.Sequential(module))
    raise OnnxExportError(f"cannot find the layers of {type(module).__name__}: pass an nn.Sequential of "
                          "Linear / ELU / ReLU / Tanh / Sigmoid (or a learn.networks.Actor)")


def _check_module_matches(module: Any, layers: list, in_dim: int) -> None:
    """The layers read out of a module must compute what its forward() computes (after clip01)."""
    import torch

    rng = np.random.default_rng(np.random.SeedSequence(20240601))
    x = rng.uniform(-1.0, 1.0, (64, in_dim)).astype(np.float32)  # (64, in_dim)
    was_training = module.training
    module.eval()  # dropout off while comparing
    try:
        with torch.no_grad():
            p = next(iter(module.parameters()), None)
            xt = torch.from_numpy(x).to(device=p.device if p is not None else "cpu",
                                        dtype=p.dtype if p is not None else torch.float32)
            y_mod = module(xt).detach().cpu().double().numpy()
    finally:
        module.train(was_training)
    y = _forward_np(layers, x)
    if y_mod.shape != y.shape:
        raise OnnxExportError(f"the module's forward returns shape {tuple(y_mod.shape)}, its layers give {y.shape}")
    err = float(np.max(np.abs(np.clip(y_mod, 0, 1) - y)))
    if err > 1e-4:
        raise OnnxExportError(f"the module's forward() differs from its Linear/activation layers by {err:.3g}; "
                              "export a plain Sequential actor")


def _forward_np(layers: Sequence[tuple[np.ndarray, np.ndarray, str]], x: np.ndarray) -> np.ndarray:
    h = np.asarray(x, np.float64)
    for w, b, a in layers:
        h = act_float(a, h @ np.asarray(w, np.float64).T + np.asarray(b, np.float64))
    return np.clip(h, 0.0, 1.0)


def _is_policy(obj: Any) -> bool:
    return all(hasattr(obj, k) for k in ("weights", "biases", "activations", "world", "t_prev"))


# --- the ONNX model --------------------------------------------------------------------------
def build_onnx_model(layers: Sequence[tuple[np.ndarray, np.ndarray, str]], world: WorldConfig, t_prev: int,
                     opset: int = DEFAULT_OPSET, extra_meta: dict[str, str] | None = None) -> Any:
    """The ModelProto for ``layers`` [(W (out, in), b (out,), activation)], checked by onnx.checker."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    top = onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= opset <= top:
        raise OnnxExportError(f"opset {opset} is not supported; choose {MIN_OPSET}..{top} (default {DEFAULT_OPSET})")
    in_dim = world.history_dim(t_prev)
    if layers[0][0].shape[1] != in_dim:
        raise OnnxExportError(f"the actor takes {layers[0][0].shape[1]} inputs but world '{world.name}' with "
                              f"t_prev={t_prev} gives {in_dim} = {t_prev} x {world.tuple_dim}")
    if layers[-1][0].shape[0] != ACTION_DIM:
        raise OnnxExportError(f"the actor outputs {layers[-1][0].shape[0]} values, not {ACTION_DIM}")
    if layers[-1][2] not in ("identity", "relu"):
        raise OnnxExportError(f"the output layer's activation is {layers[-1][2]}; kiloforge actors have a linear "
                              "output clipped to [0, 1]")

    nodes, inits = [], []
    x = INPUT_NAME
    for k, (w, b, act) in enumerate(layers):
        if act not in ACTIVATIONS:
            raise OnnxExportError(f"layer {k}: activation '{act}' is not supported ({', '.join(ACTIVATIONS)})")
        w32 = np.ascontiguousarray(w, np.float32)  # (out, in): Gemm with transB=1 reads it as is
        b32 = np.ascontiguousarray(b, np.float32)
        if k > 0 and w32.shape[1] != layers[k - 1][0].shape[0]:
            raise OnnxExportError(f"layer {k} takes {w32.shape[1]} inputs but layer {k - 1} gives {layers[k - 1][0].shape[0]}")
        inits += [numpy_helper.from_array(w32, f"layer{k}.weight"), numpy_helper.from_array(b32, f"layer{k}.bias")]
        z = f"layer{k}.linear"
        nodes.append(helper.make_node("Gemm", [x, f"layer{k}.weight", f"layer{k}.bias"], [z], name=f"layer{k}.gemm",
                                      transB=1))
        x = z
        last = k == len(layers) - 1
        if act != "identity" and not (last and act == "relu"):  # clip01 subsumes an output ReLU
            y = f"layer{k}.{act}"
            nodes.append(helper.make_node(_ONNX_ACT[act], [x], [y], name=f"layer{k}.{act}",
                                          **({"alpha": 1.0} if act == "elu" else {})))
            x = y
    inits += [numpy_helper.from_array(np.array(0.0, np.float32), "clip.min"),
              numpy_helper.from_array(np.array(1.0, np.float32), "clip.max")]
    nodes.append(helper.make_node("Clip", [x, "clip.min", "clip.max"], [OUTPUT_NAME], name="action.clip01"))

    layout = obs_layout(world)
    inp = helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["N", in_dim])
    inp.doc_string = (f"{t_prev} tuples of {world.tuple_dim}, oldest first; each tuple "
                      f"[{', '.join(layout['tuple'])}]")
    out = helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["N", ACTION_DIM])
    out.doc_string = "(u_left, u_right) in [0, 1]"
    graph = helper.make_graph(nodes, "kiloforge_actor", [inp], [out], initializer=inits,
                              doc_string="kiloforge actor: flat history -> motor commands clipped to [0, 1]")
    opsets = [helper.make_opsetid("", opset)]
    model = helper.make_model(graph, opset_imports=opsets, producer_name="kiloforge",
                              producer_version=kiloforge_version(),
                              ir_version=helper.find_min_ir_version_for(opsets))
    meta = {
        META_WORLD: world.to_json(),
        META_T_PREV: str(int(t_prev)),
        META_OBS_LAYOUT: json.dumps(layout),
        META_ACTION: "clip01",
        "kiloforge.activations": json.dumps([a for _, _, a in layers]),
        META_VERSION: kiloforge_version(),
    }
    meta.update(extra_meta or {})
    helper.set_model_props(model, meta)
    try:
        onnx.checker.check_model(model, full_check=True)
    except Exception as e:  # pragma: no cover - a bug here, not a user error
        raise OnnxExportError(f"internal error: the written model fails onnx.checker: {str(e).splitlines()[0]}") from None
    return model


def export_onnx(actor_or_policy: Any, path: str | os.PathLike, world: WorldConfig | None = None,
                t_prev: int | None = None, opset: int = DEFAULT_OPSET) -> Any:
    """Write the float actor to ``path`` as ONNX (atomically) and return the ModelProto.

    ``actor_or_policy``: a :class:`kiloforge.actors.mlp.MLPPolicy` (world and t_prev come from it; if given
    they must match) or a torch module (``learn.networks.Actor``, or an ``nn.Sequential`` of Linear /
    ELU / ReLU / Tanh / Sigmoid with a linear last layer), for which ``world`` and ``t_prev`` are required.
    """
    extra: dict[str, str] = {}
    if _is_policy(actor_or_policy):
        pol = actor_or_policy
        if world is not None and world.to_dict() != pol.world.to_dict():
            raise OnnxExportError(f"world '{world.name}' differs from the policy's world '{pol.world.name}'")
        if t_prev is not None and int(t_prev) != pol.t_prev:
            raise OnnxExportError(f"t_prev {t_prev} differs from the policy's t_prev {pol.t_prev}")
        world, t_prev = pol.world, pol.t_prev
        layers = [(np.asarray(w, np.float32), np.asarray(b, np.float32), a)
                  for w, b, a in zip(pol.weights, pol.biases, pol.activations)]
        if getattr(pol, "hash", None):
            extra["kiloforge.policy_hash"] = str(pol.hash)
    else:
        try:
            from torch import nn
        except ImportError:  # pragma: no cover
            raise OnnxExportError("exporting a torch module needs torch; or pass a policy artifact") from None
        if not isinstance(actor_or_policy, nn.Module):
            raise OnnxExportError(f"expected a Policy or a torch nn.Module, got {type(actor_or_policy).__name__}")
        if world is None or t_prev is None:
            raise OnnxExportError("exporting a torch module needs world= and t_prev= (the input layout)")
        layers = _layers_from_module(actor_or_policy)
        if layers[0][0].shape[1] == world.history_dim(int(t_prev)):
            _check_module_matches(actor_or_policy, layers, layers[0][0].shape[1])
    model = build_onnx_model(layers, world, int(t_prev), opset, extra)

    try:
        write_atomic(path, model.SerializeToString())
    except KiloforgeError as e:
        raise OnnxExportError(str(e)) from None
    return model


def check_with_onnxruntime(path: str | os.PathLike, policy: Any, n: int = 256, seed: int = 0
                           ) -> tuple[float | None, str]:
    """(max |onnxruntime(path) - policy.act| on random histories, note); (None, why) when it cannot run."""
    try:
        import onnxruntime as ort
    except ImportError:
        return None, "onnxruntime not installed, not checked"
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    x = rng.uniform(-1.0, 1.0, (n, policy.in_dim)).astype(np.float32)  # (n, in_dim)
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        y = sess.run([OUTPUT_NAME], {INPUT_NAME: x})[0]
    except Exception as e:  # e.g. an opset / IR version newer than this onnxruntime
        why = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        return None, f"onnxruntime {ort.__version__} cannot run it ({why[:160]}), not checked"
    diff = float(np.max(np.abs(y.astype(np.float64) - policy.act(x))))
    return diff, f"onnxruntime vs policy max |diff| {diff:.2e}"


def main_export_onnx(argv: list[str] | None = None) -> int:
    """``export-onnx --policy P.npz --out actor.onnx [--opset 17]``; returns the exit status."""
    from kiloforge.extras import missing_dependency
    from kiloforge.cliparse import ArgumentParser, error_line, program
    from kiloforge.interrupts import exit_status

    prog = "python -m learn export-onnx"
    ap = ArgumentParser(prog=prog,
                                 description="Write a policy artifact's float actor as an ONNX model "
                                             "(input 'history' [N, history_dim], output 'action' [N, 2] in [0, 1]).")
    ap.add_argument("--policy", required=True, help="policy artifact (.npz) written by training")
    ap.add_argument("--out", required=True, help="ONNX file to write, e.g. actor.onnx")
    ap.add_argument("--opset", type=int_arg(1, 1000), default=DEFAULT_OPSET, help=f"ONNX opset (default {DEFAULT_OPSET})")
    args = ap.parse_args(argv)
    written = False
    try:
        pol = load_policy(args.policy)
        export_onnx(pol, args.out, opset=args.opset)  # atomic: the old file or the new one
        written = True
        diff, check = check_with_onnxruntime(args.out, pol)
        return _report_onnx(prog, args, pol, diff, check)
    except KeyboardInterrupt as e:
        what = f"after writing {args.out} (complete)" if written else "; nothing written"
        print(error_line(program(prog), f"interrupted {what}".replace(" ;", ";")), file=sys.stderr)
        return exit_status(e)
    except KiloforgeError as e:
        print(error_line(program(prog), e), file=sys.stderr)
        return 2
    except ModuleNotFoundError as e:
        line = missing_dependency(program(prog), e)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return 2


def _report_onnx(prog: str, args: Any, pol: Any, diff: float | None, check: str) -> int:
    """The line of a written ONNX file, and exit status 1 when onnxruntime disagrees with the policy."""
    from kiloforge.cliparse import error_line, program

    sizes = " -> ".join(str(s) for s in pol.layer_sizes)
    print(f"wrote {args.out}: {sizes} ({', '.join(pol.activations)}), opset {args.opset}, world '{pol.world.name}', "
          f"t_prev {pol.t_prev}; {check}")
    if diff is not None and diff > 1e-4:
        print(error_line(program(prog), f"onnxruntime output differs from the policy by {diff:.3g}"), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main_export_onnx())
