"""Will it fit? An analytic flash / SRAM breakdown of the generated Kilobot firmware.

The hard gates (DESIGN.md "Budgets", ``../shared/reference/kilobot-platform.md``):

* flash: text + data of the whole program, kilolib included, <= 28,160 B (KiloGUI sends at most
  220 pages of 128 B);
* user SRAM: .data + .bss + peak stack of the control step <= 1,536 B (kilolib's own 110 B static,
  its ISR stack and the main frames live in the remaining 512 B of the 2 KB).

The breakdown is analytic: the sizes of everything that is data, laid out as the renderer lays it
out (int8 weights, int32 biases, uint8 shifts, the RBF table trimmed to each bin's non-zero window and
the target table to its clamp index by :mod:`export.cformat`, activation tables, ring buffer,
neighbour table, ...) and a documented estimate for the code (:data:`CODE_ESTIMATE_B`) and the
control step's stack. ``export/avr.py`` can merge the exact figures of a real avr-gcc build into
:attr:`Budget.exact`; when present they decide.

>>> from sim.config import preset
>>> b = estimate(preset("kilobot"), 10, (32, 32))
>>> b.ok, b.flash_total < FLASH_LIMIT_B
(True, True)
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Sequence

from sim.config import ACTION_DIM, WorldConfig

from . import numfmt
from .cformat import clamp_index_table, nonzero_windows

if TYPE_CHECKING:  # pragma: no cover
    from .artifact import Policy
    from .quantize import QuantizedPolicy

# --- limits (DESIGN.md "Budgets") -----------------------------------------------------------------
FLASH_LIMIT_B = 28_160  #: text + data, whole program (220 pages x 128 B that KiloGUI uploads)
SRAM_LIMIT_B = 1_536  #: user .data + .bss + peak control-step stack
SRAM_TOTAL_B = 2_048  #: ATmega328P SRAM

# --- kilolib (measured, platform notes) -----------------------------------------------------------
KILOLIB_FLASH_B = 7_028  #: kilolib with empty setup/loop (avr-gcc 5.4 -O3), includes crt + vectors
KILOLIB_SRAM_STATIC_B = 110  #: kilolib .data + .bss
KILOLIB_ISR_STACK_B = 75  #: peak stack of kilolib's interrupt handlers (rx callback runs inside)
KILOLIB_MAIN_FRAMES_B = 10  #: main / kilo_start frames

# --- code estimate ------------------------------------------------------------------------------
#: Bytes of AVR code of our program besides kilolib (avr-gcc 5.4, -O3 with the kilolib flags), until
#: ``export/avr.py`` calibrates them from real builds. Source: kiloforge's rendered firmware compiled
#: to an object file: .text 5,064-5,302 B for 2 to 5 dense layers (the C kernel and the AVR assembly
#: kernel are shared by every layer; a layer adds ~22 B of code), rounded up, plus ~200 B for the
#: libgcc helpers (32-bit multiply and shifts) linked in at build time.
CODE_ESTIMATE_B: dict[str, int] = {
    "base": 5_500,  #: setup/loop/rate limit, rx ISR + queue, neighbour table, observe, ring buffer, both
                    #: dense kernels, motor schedule, message + CRC, beacon role, libgcc helpers
    "per_layer": 25,  #: one more dense layer (its call and activation step)
}
LAYER_DESCRIPTOR_B = 15  #: per layer: the kernel's layer struct (initialised .data: flash and SRAM)

# --- SRAM estimate --------------------------------------------------------------------------------
RX_QUEUE_LEN = 8  #: messages buffered between the rx ISR and loop()
RX_ENTRY_B = 8  #: uid (2) + raw distance_measurement_t (4) + role/flag (1) + tick (1)
NEIGHBOUR_ENTRY_B = 4  #: uid (2) + distance (1) + sensing flag (1)
MESSAGE_B = 12  #: message_t (9 payload + type + crc16), packed
MISC_STATE_B = 32  #: tick counters, previous command, wall flag, target slot, schedule, role, heads
CONTROL_STACK_B = 80  #: estimated peak stack of the control step (frames + saved registers)

TABLE_ACTIVATIONS = ("elu", "tanh", "sigmoid")  #: each costs one 256-entry int8 table (identical ones shared)


@dataclass(frozen=True)
class Item:
    """One line of the breakdown."""

    section: str  #: "flash" or "sram"
    name: str
    bytes: int
    note: str = ""


@dataclass(frozen=True)
class Budget:
    """Flash / SRAM breakdown of one architecture in one world; ``ok`` says whether it fits."""

    world: WorldConfig
    t_prev: int
    layer_sizes: tuple[int, ...]  #: (in_dim, hidden..., 2)
    activations: tuple[str, ...]  #: one per layer
    items: tuple[Item, ...]
    exact: dict[str, Any] | None = None  #: avr-gcc figures (keys "flash", "sram_user", ...) from export/avr.py
    flash_limit: int = FLASH_LIMIT_B
    sram_limit: int = SRAM_LIMIT_B
    kind: str = "mlp"  #: "mlp", or "gru": a recurrent actor (layer_sizes (in, hidden, 2), t_prev 1)

    # --- totals ------------------------------------------------------------------------------
    @property
    def flash_analytic(self) -> int:
        return sum(i.bytes for i in self.items if i.section == "flash")

    @property
    def sram_analytic(self) -> int:
        return sum(i.bytes for i in self.items if i.section == "sram")

    @property
    def flash_total(self) -> int:
        """Whole-program flash (text + data): exact when a real build was merged in."""
        if self.exact and "flash" in self.exact:
            return int(self.exact["flash"])
        return self.flash_analytic

    @property
    def sram_total(self) -> int:
        """User SRAM (.data + .bss + control-step stack): exact when a real build was merged in."""
        if self.exact and "sram_user" in self.exact:
            return int(self.exact["sram_user"])
        return self.sram_analytic

    @property
    def flash_ok(self) -> bool:
        return self.flash_total <= self.flash_limit

    @property
    def sram_ok(self) -> bool:
        return self.sram_total <= self.sram_limit

    @property
    def ok(self) -> bool:
        return self.flash_ok and self.sram_ok

    @property
    def hidden(self) -> tuple[int, ...]:
        return tuple(self.layer_sizes[1:-1])

    def with_exact(self, exact: dict[str, Any]) -> "Budget":
        """A copy with real-build figures merged in (used by export/avr.py)."""
        return replace(self, exact=dict(exact))

    # --- presentation ------------------------------------------------------------------------
    def table(self) -> str:
        """A printable breakdown."""
        arch = " -> ".join(map(str, self.layer_sizes))
        lines = [f"budget: world '{self.world.name}', t_prev {self.t_prev}, layers {arch} "
                 f"({', '.join(self.activations)})"]
        if self.kind == "gru":
            lines = [f"budget: world '{self.world.name}', GRU actor: input {self.layer_sizes[0]}, "
                     f"{self.layer_sizes[1]} hidden units (int8 state), linear output {self.layer_sizes[2]}"]
        for section, total, limit in (("flash", self.flash_analytic, self.flash_limit),
                                      ("sram", self.sram_analytic, self.sram_limit)):
            lines.append(f"  {section.upper()} (analytic)")
            for i in self.items:
                if i.section == section:
                    lines.append(f"    {i.name:<34} {i.bytes:>7,d} B  {i.note}")
            lines.append(f"    {'total':<34} {total:>7,d} B  of {limit:,d} B "
                         f"({100.0 * total / limit:.1f}%, {limit - total:+,d} B)")
        lines.append(f"  not in the user SRAM budget: kilolib static {KILOLIB_SRAM_STATIC_B} B, ISR stack "
                     f"~{KILOLIB_ISR_STACK_B} B, main frames ~{KILOLIB_MAIN_FRAMES_B} B "
                     f"(device total {self.sram_analytic + KILOLIB_SRAM_STATIC_B + KILOLIB_ISR_STACK_B + KILOLIB_MAIN_FRAMES_B:,d} "
                     f"of {SRAM_TOTAL_B:,d} B)")
        if self.exact:
            shown = ", ".join(f"{k} {v:,}" if isinstance(v, int) else f"{k} {v}" for k, v in self.exact.items())
            lines.append(f"  avr-gcc build: {shown}")
        verdict = "FITS" if self.ok else "DOES NOT FIT"
        lines.append(f"  {verdict}: flash {self.flash_total:,d} / {self.flash_limit:,d} B, "
                     f"user SRAM {self.sram_total:,d} / {self.sram_limit:,d} B")
        return "\n".join(lines)

    def summary(self) -> str:
        """One line: verdict and the two totals."""
        return (f"flash {self.flash_total:,d} / {self.flash_limit:,d} B, user SRAM {self.sram_total:,d} / "
                f"{self.sram_limit:,d} B: {'fits' if self.ok else 'does not fit'}")

    def suggest(self) -> list[str]:
        """What would fit: the largest history at these hidden sizes, the largest width at this history."""
        acts_h = self.activations[:-1]
        out = []
        if self.kind == "gru":
            best = largest_gru_hidden(self.world)
            return [f"a GRU of <= {best} hidden units" if best else "no GRU size fits"]
        t_best = largest_t_prev(self.world, self.hidden, acts_h)
        if t_best:
            out.append(f"t_prev <= {t_best} with hidden {list(self.hidden)}")
        else:
            out.append(f"no history length fits with hidden {list(self.hidden)}")
        if self.hidden:
            w_best = largest_width(self.world, self.t_prev, len(self.hidden), acts_h)
            if w_best:
                out.append(f"hidden {[w_best] * len(self.hidden)} with t_prev {self.t_prev}")
            else:
                out.append(f"no hidden width fits with t_prev {self.t_prev}")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "world": self.world.name, "t_prev": self.t_prev, "layer_sizes": list(self.layer_sizes),
            "activations": list(self.activations),
            "flash": {"analytic": self.flash_analytic, "total": self.flash_total, "limit": self.flash_limit,
                      "items": {i.name: i.bytes for i in self.items if i.section == "flash"}},
            "sram_user": {"analytic": self.sram_analytic, "total": self.sram_total, "limit": self.sram_limit,
                          "items": {i.name: i.bytes for i in self.items if i.section == "sram"}},
            "exact": self.exact, "fits": self.ok,
            "code_estimate_b": dict(CODE_ESTIMATE_B),
            **({"kind": self.kind, "gru_code_b": GRU_CODE_B} if self.kind != "mlp" else {}),
        }


def _acts(hidden: Sequence[int], activations: Sequence[str] | None) -> tuple[str, ...]:
    if activations is None:
        return tuple(["elu"] * len(hidden) + ["identity"])
    acts = tuple(activations)
    if len(acts) == len(hidden):  # hidden activations only
        acts = acts + ("identity",)
    assert len(acts) == len(hidden) + 1, f"{len(acts)} activations for {len(hidden) + 1} layers"
    return acts


def sensing_table_bytes(world: WorldConfig, e_in: int = numfmt.DEFAULT_INPUT_EXP) -> tuple[int, int]:
    """(RBF bytes, target-table bytes) as rendered: non-zero windows + their lo/len/offset; clamped prefix."""
    rbf = numfmt.rbf_table(world.rbf_centres_mm, world.rbf_sigma_mm, world.rbf_norm, world.comm_radius_mm, e_in)
    _, _, _, packed = nonzero_windows(rbf)
    tgt, _ = clamp_index_table(numfmt.target_table(world.comm_radius_mm, e_in))
    return int(packed.size) + 5 * world.n_rbf, int(tgt.size)  # lo uint8, len + offset uint16 per bin


def estimate(world: WorldConfig, t_prev: int, hidden: Sequence[int],
             activations: Sequence[str] | None = None, *, e_in: int = numfmt.DEFAULT_INPUT_EXP,
             n_act_tables: int | None = None, n_target_uids: int = 1) -> Budget:
    """Analytic budget of an actor with ``t_prev`` history tuples and ``hidden`` layer widths.

    ``activations``: one per layer (or one per hidden layer); default ELU hidden, identity output.
    ``e_in`` (the input exponent) shapes the trimmed sensing tables; ``n_act_tables`` overrides the
    count of activation tables (a quantised policy knows which are identical and shared);
    ``n_target_uids``: kilo_uids that run the beacon role (a uint16 table).
    """
    assert t_prev >= 1, f"t_prev must be >= 1, got {t_prev}"
    assert all(h >= 1 for h in hidden), f"hidden widths must be >= 1, got {list(hidden)}"
    acts = _acts(hidden, activations)
    sizes = (world.history_dim(t_prev), *map(int, hidden), ACTION_DIM)
    n_layers = len(sizes) - 1
    n_w = sum(sizes[k] * sizes[k + 1] for k in range(n_layers))
    n_rows = sum(sizes[1:])
    n_tables = sum(1 for a in acts[:-1] if a in TABLE_ACTIVATIONS) if n_act_tables is None else n_act_tables
    rbf_b, tgt_b = sensing_table_bytes(world, e_in)
    x_len = max(sizes[1:-1], default=1)  # widest hidden activation (int8)
    y_len = max(sizes[1:])  # widest layer output (int16)
    items = [
        Item("flash", "kilolib", KILOLIB_FLASH_B, "measured, empty setup/loop"),
        Item("flash", "program code (estimate)",
             CODE_ESTIMATE_B["base"] + CODE_ESTIMATE_B["per_layer"] * n_layers,
             f"{CODE_ESTIMATE_B['base']} + {CODE_ESTIMATE_B['per_layer']} x {n_layers} layers"),
        Item("flash", "layer descriptors", LAYER_DESCRIPTOR_B * n_layers, f"{LAYER_DESCRIPTOR_B} x {n_layers} (.data)"),
        Item("flash", "weights int8", n_w, " + ".join(f"{sizes[k + 1]}x{sizes[k]}" for k in range(n_layers))),
        Item("flash", "biases int32", 4 * n_rows, f"4 x {n_rows} rows"),
        Item("flash", "shifts uint8", n_rows, f"1 x {n_rows} rows"),
        Item("flash", "RBF table", rbf_b, f"{world.n_rbf} non-zero windows + index, e_in {e_in}"),
        Item("flash", "target, action, uid tables", tgt_b + 256 + 2 * n_target_uids,
             f"{tgt_b} + 256 int8 + {n_target_uids} uint16"),
        Item("flash", "activation tables", 256 * n_tables, f"{n_tables} x 256 int8"),
        Item("sram", "history ring buffer", t_prev * world.tuple_dim, f"{t_prev} x {world.tuple_dim} int8"),
        Item("sram", "neighbour table", world.neighbour_table_size * NEIGHBOUR_ENTRY_B,
             f"{world.neighbour_table_size} x {NEIGHBOUR_ENTRY_B} B"),
        Item("sram", "rx queue", RX_QUEUE_LEN * RX_ENTRY_B, f"{RX_QUEUE_LEN} x {RX_ENTRY_B} B"),
        Item("sram", "outgoing message", MESSAGE_B, "message_t"),
        Item("sram", "misc state", MISC_STATE_B, "estimate"),
        Item("sram", "activation buffers", x_len + 2 * y_len, f"{x_len} int8 + {y_len} int16"),
        Item("sram", "layer descriptors", LAYER_DESCRIPTOR_B * n_layers, f"{LAYER_DESCRIPTOR_B} x {n_layers}"),
        Item("sram", "control-step stack (estimate)", CONTROL_STACK_B, "estimate"),
    ]
    return Budget(world=world, t_prev=int(t_prev), layer_sizes=tuple(sizes), activations=acts, items=tuple(items))


def fits(world: WorldConfig, t_prev: int, hidden: Sequence[int],
         activations: Sequence[str] | None = None) -> Budget:
    """Same as :func:`estimate` (read ``.ok``); named for the question it answers."""
    return estimate(world, t_prev, hidden, activations)


def for_policy(policy: "Policy") -> Budget:
    """The budget of a float policy's architecture."""
    if getattr(policy, "kind", "mlp") == "gru":  # a recurrent actor (export/gru.py)
        return estimate_gru(policy.world, policy.hidden_size)
    return estimate(policy.world, policy.t_prev, policy.hidden, policy.activations)


def for_quantized(qp: "QuantizedPolicy") -> Budget:
    """The budget of a quantised policy: its e_in, and its distinct activation tables."""
    if getattr(qp, "kind", "mlp") == "gru":  # a recurrent actor (export/gru_quantize.py)
        return estimate_gru(qp.world, qp.hidden_size, e_in=qp.e_in)
    acts = [l.activation for l in qp.layers]
    distinct = {l.table.tobytes() for l in qp.layers if l.table is not None}
    return estimate(qp.world, qp.t_prev, qp.layer_sizes[1:-1], acts, e_in=qp.e_in, n_act_tables=len(distinct))


def largest_t_prev(world: WorldConfig, hidden: Sequence[int], activations: Sequence[str] | None = None,
                   cap: int = 1024) -> int:
    """Largest t_prev (<= cap) that fits with these hidden sizes; 0 when none does."""
    best = 0
    for t in range(1, cap + 1):  # budgets grow with t_prev: stop at the first failure
        if not estimate(world, t, hidden, activations).ok:
            break
        best = t
    return best


def largest_width(world: WorldConfig, t_prev: int, n_hidden: int, activations: Sequence[str] | None = None,
                  cap: int = 1024) -> int:
    """Largest uniform hidden width (``n_hidden`` layers, <= cap) that fits at ``t_prev``; 0 when none."""
    best = 0
    for w in range(1, cap + 1):
        if not estimate(world, t_prev, [w] * n_hidden, activations).ok:
            break
        best = w
    return best


# --- the recurrent actor (export/gru_quantize.py, firmware_templates/kilobot_policy_gru.c.j2) ------
GRU_LAYERS = 5  #: dense layers of the int8 GRU: r and z gates over [x, h], n's input and hidden parts, output
GRU_CODE_B = 300  #: code of the GRU step beyond the dense calls (gate tables, n, state update); estimate
GRU_GATE_TABLES_B = 3 * 256  #: sigmoid (r), 1 - sigmoid (1 - z) uint8 and tanh int8 tables


def gru_sizes(in_dim: int, hidden: int) -> list[tuple[int, int]]:
    """(n_out, n_in) of the five dense layers: r, z over [x, h]; n over x; n over h; the output.

    >>> gru_sizes(16, 32)
    [(32, 48), (32, 48), (32, 16), (32, 32), (2, 32)]
    """
    D, H = int(in_dim), int(hidden)
    return [(H, D + H), (H, D + H), (H, D), (H, H), (ACTION_DIM, H)]


def estimate_gru(world: WorldConfig, hidden: int, *, e_in: int = numfmt.DEFAULT_INPUT_EXP,
                 n_target_uids: int = 1) -> Budget:
    """Analytic budget of the int8 GRU actor with ``hidden`` units (one tuple of input per step).

    >>> from sim.config import preset
    >>> estimate_gru(preset("kilobot"), 32).ok
    True
    """
    assert hidden >= 1, f"hidden must be >= 1, got {hidden}"
    D, H = world.tuple_dim, int(hidden)
    layers = gru_sizes(D, H)
    n_w = sum(o * i for o, i in layers)
    n_rows = sum(o for o, _ in layers)
    rbf_b, tgt_b = sensing_table_bytes(world, e_in)
    items = [
        Item("flash", "kilolib", KILOLIB_FLASH_B, "measured, empty setup/loop"),
        Item("flash", "program code (estimate)",
             CODE_ESTIMATE_B["base"] + CODE_ESTIMATE_B["per_layer"] * GRU_LAYERS + GRU_CODE_B,
             f"{CODE_ESTIMATE_B['base']} + {CODE_ESTIMATE_B['per_layer']} x {GRU_LAYERS} layers + {GRU_CODE_B} GRU step"),
        Item("flash", "layer descriptors", LAYER_DESCRIPTOR_B * GRU_LAYERS, f"{LAYER_DESCRIPTOR_B} x {GRU_LAYERS} (.data)"),
        Item("flash", "weights int8", n_w, " + ".join(f"{o}x{i}" for o, i in layers)),
        Item("flash", "biases int32", 4 * n_rows, f"4 x {n_rows} rows"),
        Item("flash", "shifts uint8", n_rows, f"1 x {n_rows} rows"),
        Item("flash", "RBF table", rbf_b, f"{world.n_rbf} non-zero windows + index, e_in {e_in}"),
        Item("flash", "target, action, uid tables", tgt_b + 256 + 2 * n_target_uids,
             f"{tgt_b} + 256 int8 + {n_target_uids} uint16"),
        Item("flash", "gate tables", GRU_GATE_TABLES_B, "sigmoid, 1 - sigmoid (uint8), tanh (int8)"),
        Item("sram", "hidden state + input", H + D, f"{H} + {D} int8"),
        Item("sram", "neighbour table", world.neighbour_table_size * NEIGHBOUR_ENTRY_B,
             f"{world.neighbour_table_size} x {NEIGHBOUR_ENTRY_B} B"),
        Item("sram", "rx queue", RX_QUEUE_LEN * RX_ENTRY_B, f"{RX_QUEUE_LEN} x {RX_ENTRY_B} B"),
        Item("sram", "outgoing message", MESSAGE_B, "message_t"),
        Item("sram", "misc state", MISC_STATE_B, "estimate"),
        Item("sram", "gate buffers", 2 * 2 * H + H, f"{2 * H} int16 + {H} uint8"),
        Item("sram", "layer descriptors", LAYER_DESCRIPTOR_B * GRU_LAYERS, f"{LAYER_DESCRIPTOR_B} x {GRU_LAYERS}"),
        Item("sram", "control-step stack (estimate)", CONTROL_STACK_B, "estimate"),
    ]
    return Budget(world=world, t_prev=1, layer_sizes=(D, H, ACTION_DIM), activations=("gru", "identity"),
                  items=tuple(items), kind="gru")


def largest_gru_hidden(world: WorldConfig, cap: int = 255) -> int:
    """Largest GRU hidden size (<= cap) that fits; 0 when none does."""
    best = 0
    for h in range(1, cap + 1):
        if not estimate_gru(world, h).ok:
            break
        best = h
    return best
