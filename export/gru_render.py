"""The renderer's context for a recurrent policy: ``kilobot_policy_gru.c.j2`` (see :mod:`export.render`).

The GRU program is the MLP program (``kilobot_policy.c.j2``, which it extends) with the history
ring buffer replaced by one input tuple and the int8 hidden state, and ``kf_forward`` replaced by
the GRU step of ``firmware_templates/kf_gru.h`` between five ``kf_dense`` layers (r and z over
``[x, h]`` without copying, n's input and hidden parts, the output layer). Every number comes from
:class:`export.gru_quantize.QuantizedGRU`; the emulator models it through ``QuantizedGRU.step_int``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from . import kernel, numfmt
from .cformat import c_array
from .errors import ExportError

if TYPE_CHECKING:  # pragma: no cover
    from .gru_quantize import QuantizedGRU

TEMPLATE = "kilobot_policy_gru.c.j2"
GRU_SOURCES = ("kf_gru.h",)
#: (C name suffix, QuantizedGRU.layers index, what the layer computes) in firmware order
LAYERS = (("R", 0, "a_r = W_r [x, h] + b_r (h columns scaled by 2^(e_in - 7))"),
          ("Z", 1, "a_z = W_z [x, h] + b_z (h columns scaled by 2^(e_in - 7))"),
          ("NX", 2, "W_in x + b_in"),
          ("NH", 3, "W_hn h + b_hn"),
          ("OUT", 4, "255 u = W_out h + b_out (the uint8 motor commands)"))


def gru_policy_context(qp: "QuantizedGRU", uids: tuple[int, ...]) -> dict[str, Any]:
    """Template variables of the recurrent policy program (defines, tables, layers, GRU C)."""
    from .render import _define, _io_context, _u, inline_sources

    H, c = qp.hidden_size, qp.cell
    if not 1 <= H <= 255:
        raise ExportError(f"a GRU of {H} hidden units does not fit the firmware's uint8 loops (1..255)")
    defines, tables = _io_context(qp, uids, [_define("KF_HIDDEN", _u(H), "GRU hidden units (int8 state at exponent 7)")], [
        _define("KF_Y_LEN", _u(2 * H, "uint16_t"), "scratch: two gate vectors (int16)"),
        _define("KF_RN_SHIFT", _u(c.rn_shift), f"r * (W_hn h + b_hn): exponent {numfmt.GATE_EXP} + e_nh "
                                                f"{c.nh.e_out} -> e_n {c.e_n}"),
        _define("KF_NX_SHIFT", _u(c.nx_shift), f"W_in x + b_in: exponent e_nx {c.nx.e_out} -> e_n {c.e_n} (left shift)"),
    ])
    tables += [
        c_array("KF_GATE_R", "uint8_t", c.r_table,
                comment=f"r = sigmoid(a_r) at exponent {numfmt.GATE_EXP}; index a_r + 128, a_r at exponent {c.r.e_out}"),
        c_array("KF_GATE_K", "uint8_t", c.k_table,
                comment=f"k = 1 - sigmoid(a_z) at exponent {numfmt.GATE_EXP}; index a_z + 128, a_z at exponent {c.z.e_out}"),
        c_array("KF_TANH", "int8_t", c.n_table,
                comment=f"n = tanh(p) at exponent {numfmt.HIDDEN_EXP}; index p + 128, p at exponent {c.e_n}"),
    ]
    layers = []
    for name, k, what in LAYERS:
        layer = qp.layers[k]
        n_out, n_in = (int(v) for v in layer.w.shape)
        kl = kernel.kernel_layer(layer)
        tables += [
            c_array(f"KF_W_{name}", "int8_t", kl.w, comment=f"{what}: {n_out} x {n_in} weights in kernel order "
                                                            f"(export/kernel.py), input exponent {layer.e_in}"),
            c_array(f"KF_B_{name}", "int32_t", kl.b, per_line=8, comment=f"{name}: folded int32 biases (export/kernel.py)"),
            c_array(f"KF_S_{name}", "uint8_t", kl.shift, comment=f"{name}: requantisation shifts to exponent {layer.e_out}"),
        ]
        layers.append({"name": f"KF_L{name}", "init": kl.c_initializer(f"KF_W_{name}", f"KF_B_{name}", f"KF_S_{name}"),
                       "n_out": _u(n_out, "uint16_t"), "act": "identity", "table": "",
                       "fast": "yes" if kl.fast else "no"})
    return {"defines": defines, "tables": tables, "layers": layers, "gru_c": inline_sources(GRU_SOURCES)}
