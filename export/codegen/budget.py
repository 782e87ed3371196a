"""Will it fit? An analytic flash / SRAM breakdown of the generated Kilobot firmware.

The hard gates (docs/design.md "Budgets", the Kilobot platform notes):

* flash: text + data of the whole program, kilolib included, <= 28,160 B (KiloGUI sends at most
  220 pages of 128 B);
* user SRAM: .data + .bss + peak stack of the control step <= 1,536 B (kilolib's own 110 B static,
  its ISR stack and the main frames live in the remaining 512 B of the 2 KB).

The breakdown is analytic: the sizes of everything that is data, laid out as the renderer lays it
out (int8 weights, int32 biases, uint8 shifts of every dense layer, the RBF table trimmed to each
bin's non-zero window and the target table to its clamp index by :mod:`export.codegen.cformat`,
neighbour table, rx queue, ...), the actor kind's own items (:meth:`ActorKind.budget_spec`: its
tables, state and buffers) and a documented estimate for the code (:data:`CODE_ESTIMATE_B`) and
the control step's stack. :mod:`export.verify.avr` can merge the exact figures of a real avr-gcc
build into :attr:`Budget.exact`; when present they decide.

>>> from sim.config import preset
>>> from kiloforge.actors.mlp import MLP, MLPArch
>>> b = estimate(MLP, preset("kilobot"), MLPArch(10, (32, 32)))
>>> b.ok, b.flash_total < FLASH_LIMIT_B
(True, True)
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from kiloforge import numfmt
from kiloforge.actors.base import ActorKind, BudgetItem, FloatPolicy, QuantizedActor, Resize
from kiloforge.actors.registry import kind_of
from sim.config import WorldConfig
from sim.features import emitter_sends_light, feature

from ..contract import firmware as fw
from .cformat import clamp_index_table, nonzero_windows

# --- limits (docs/design.md "Budgets") ----------------------------------------------------------
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
#: ``export/verify/avr.py`` calibrates them from real builds. Source: kiloforge's rendered firmware
#: compiled to an object file: .text 5,064-5,302 B for 2 to 5 dense layers (the C kernel and the AVR
#: assembly kernel are shared by every layer; a layer adds ~22 B of code), rounded up, plus ~200 B for
#: the libgcc helpers (32-bit multiply and shifts) linked in at build time.
CODE_ESTIMATE_B: dict[str, int] = {
    "base": 5_500,  #: setup/loop/rate limit, rx ISR + queue, neighbour table, observe, actor input, both
                    #: dense kernels, motor schedule, message + CRC, role switch, libgcc helpers
    "per_layer": 25,  #: one more dense layer (its call and activation step)
}
LAYER_DESCRIPTOR_B = 15  #: per layer: the kernel's layer struct (initialised .data: flash and SRAM)

# --- SRAM estimate --------------------------------------------------------------------------------
RX_ENTRY_B = 8  #: uid (2) + raw distance_measurement_t (4) + role/flag (1) + tick (1)
NEIGHBOUR_ENTRY_B = 4  #: uid (2) + distance (1) + sensing flag (1, only when a feature reads it)
EMITTER_LIGHT_RX_B = 2  #: an rx entry's emitter light reading (worlds where the emitter sends it: object_light)
EMITTER_LIGHT_STATE_B = 4  #: the held object_light level and flag, the emitter role's held reading
MISC_STATE_B = 32  #: tick counters, previous command, wall flag, target slot, schedule, role, heads
CONTROL_STACK_B = 80  #: estimated peak stack of the control step (frames + saved registers)


@dataclass(frozen=True)
class Budget:
    """Flash / SRAM breakdown of one architecture of one actor kind in one world; ``ok``: it fits."""

    world: WorldConfig
    kind: ActorKind
    arch: Any  #: the kind's architecture (what its budget_spec took)
    header: str  #: the architecture in words
    layer_sizes: tuple[int, ...]  #: (input, hidden..., 2)
    items: tuple[BudgetItem, ...]
    arch_dict: dict[str, Any]  #: JSON-ready sizes
    exact: dict[str, Any] | None = None  #: avr-gcc figures (keys "flash", "sram_user", ...) from export/verify/avr.py
    flash_limit: int = FLASH_LIMIT_B
    sram_limit: int = SRAM_LIMIT_B

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

    def with_exact(self, exact: dict[str, Any]) -> "Budget":
        """A copy with real-build figures merged in (used by export/verify/avr.py)."""
        return replace(self, exact=dict(exact))

    # --- presentation ------------------------------------------------------------------------
    def table(self) -> str:
        """A printable breakdown."""
        lines = [f"budget: world '{self.world.name}', {self.header}"]
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
        """What would fit: for each size the kind varies, the largest value that fits."""
        out = []
        for r in self.kind.resizes(self.world, self.arch):
            best = largest(self.kind, self.world, r)
            out.append(r.found(best) if best else r.none)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "world": self.world.name, "kind": self.kind.name, "arch": dict(self.arch_dict),
            "layer_sizes": list(self.layer_sizes),
            "flash": {"analytic": self.flash_analytic, "total": self.flash_total, "limit": self.flash_limit,
                      "items": {i.name: i.bytes for i in self.items if i.section == "flash"}},
            "sram_user": {"analytic": self.sram_analytic, "total": self.sram_total, "limit": self.sram_limit,
                          "items": {i.name: i.bytes for i in self.items if i.section == "sram"}},
            "exact": self.exact, "fits": self.ok,
            "code_estimate_b": dict(CODE_ESTIMATE_B),
        }


def sensing_table_bytes(world: WorldConfig, e_in: int = numfmt.DEFAULT_INPUT_EXP) -> tuple[int, int]:
    """(RBF bytes, target-table bytes) as rendered: non-zero windows + their lo/len/offset; clamped prefix.
    0 for a table the world's observation layout does not read (it is not rendered)."""
    rbf_b = tgt_b = 0
    if world.has_feature("rbf"):
        rbf = numfmt.rbf_table(world.rbf_centres_mm, world.rbf_sigma_mm, world.rbf_norm, world.comm_radius_mm, e_in)
        _, _, _, packed = nonzero_windows(rbf)
        rbf_b = int(packed.size) + 5 * world.n_rbf  # lo uint8, len + offset uint16 per bin
    if world.has_feature("target"):
        tgt, _ = clamp_index_table(numfmt.target_table(world.comm_radius_mm, e_in))
        tgt_b = int(tgt.size)
    return rbf_b, tgt_b


def neighbour_entry_bytes(world: WorldConfig) -> int:
    """One neighbour-table entry as rendered: the sensing flag only when a feature reads it."""
    return NEIGHBOUR_ENTRY_B - (not any(feature(f).uses_flag for f in world.features))


def estimate(kind: ActorKind, world: WorldConfig, arch: Any, *, e_in: int = numfmt.DEFAULT_INPUT_EXP,
             n_role_uids: int = 1) -> Budget:
    """Analytic budget of an actor of ``kind`` with architecture ``arch`` (the kind's size type).

    ``e_in`` (the input exponent) shapes the trimmed sensing tables; ``n_role_uids``: kilo_uids that
    take the task's role (a uint16 table; none in a world without roles, :attr:`sim.config.WorldConfig.has_roles`).
    Only what the world's roles and observation layout render is counted.
    """
    if not world.has_roles:
        n_role_uids = 0
    spec = kind.budget_spec(world, arch, e_in)
    n_layers = len(spec.dense)
    n_w = sum(o * i for o, i in spec.dense)
    n_rows = sum(o for o, _ in spec.dense)
    rbf_b, tgt_b = sensing_table_bytes(world, e_in)
    light_msg = emitter_sends_light(world)
    rx_b = RX_ENTRY_B + EMITTER_LIGHT_RX_B * light_msg
    misc_b = MISC_STATE_B + EMITTER_LIGHT_STATE_B * light_msg
    code_note = f"{CODE_ESTIMATE_B['base']} + {CODE_ESTIMATE_B['per_layer']} x {n_layers} layers"
    if spec.code_b:
        code_note += f" + {spec.code_b} {spec.code_note}"
    items = [
        BudgetItem("flash", "kilolib", KILOLIB_FLASH_B, "measured, empty setup/loop"),
        BudgetItem("flash", "program code (estimate)",
             CODE_ESTIMATE_B["base"] + CODE_ESTIMATE_B["per_layer"] * n_layers + spec.code_b, code_note),
        BudgetItem("flash", "layer descriptors", LAYER_DESCRIPTOR_B * n_layers, f"{LAYER_DESCRIPTOR_B} x {n_layers} (.data)"),
        BudgetItem("flash", "weights int8", n_w, " + ".join(f"{o}x{i}" for o, i in spec.dense)),
        BudgetItem("flash", "biases int32", 4 * n_rows, f"4 x {n_rows} rows"),
        BudgetItem("flash", "shifts uint8", n_rows, f"1 x {n_rows} rows"),
        *([BudgetItem("flash", "RBF table", rbf_b, f"{world.n_rbf} non-zero windows + index, e_in {e_in}")]
          if world.has_feature("rbf") else []),
        BudgetItem("flash", "target, action, uid tables", tgt_b + numfmt.TABLE_SIZE + 2 * n_role_uids,
             f"{tgt_b} + {numfmt.TABLE_SIZE} int8 + {n_role_uids} uint16"),
        *spec.flash,
        *spec.memory,
        BudgetItem("sram", "neighbour table", world.neighbour_table_size * neighbour_entry_bytes(world),
             f"{world.neighbour_table_size} x {neighbour_entry_bytes(world)} B"),
        BudgetItem("sram", "rx queue", fw.RXQ_CAPACITY * rx_b, f"{fw.RXQ_CAPACITY} x {rx_b} B"),
        BudgetItem("sram", "outgoing message", fw.MSG_BYTES, "message_t"),
        BudgetItem("sram", "misc state", misc_b, "estimate"),
        *spec.scratch,
        BudgetItem("sram", "layer descriptors", LAYER_DESCRIPTOR_B * n_layers, f"{LAYER_DESCRIPTOR_B} x {n_layers}"),
        BudgetItem("sram", "control-step stack (estimate)", CONTROL_STACK_B, "estimate"),
    ]
    return Budget(world=world, kind=kind, arch=arch, header=spec.header, layer_sizes=tuple(spec.layer_sizes),
                  items=tuple(items), arch_dict=dict(spec.arch))


def for_policy(policy: FloatPolicy) -> Budget:
    """The budget of a float policy's architecture."""
    kind = kind_of(policy)
    return estimate(kind, policy.world, kind.arch_of(policy))


def for_quantized(qp: QuantizedActor) -> Budget:
    """The budget of a quantised policy: its e_in, and what its kind knows (e.g. shared tables)."""
    kind = kind_of(qp)
    return estimate(kind, qp.world, kind.arch_of_quantized(qp), e_in=qp.e_in)


def largest(kind: ActorKind, world: WorldConfig, resize: Resize) -> int:
    """Largest n (<= resize.cap) whose architecture ``resize.arch(n)`` fits; 0 when n = 1 does not."""
    best = 0
    for n in range(1, resize.cap + 1):  # budgets grow with every size: stop at the first failure
        if not estimate(kind, world, resize.arch(n)).ok:
            break
        best = n
    return best
