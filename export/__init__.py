"""The exporter: a policy artifact to one int8 C file for the Kilobot, and the proof that it behaves.

Stages: :mod:`export.quantize` (calibration rollouts, the kind's quantiser), :mod:`export.codegen`
(C formatting, templates, renderer, dense kernel, budget, manifest), :mod:`export.verify`
(emulator, host build, AVR and simavr, closed loop), :mod:`export.interop` (ONNX in);
:mod:`export.contract` holds what the C, the emulator and the harnesses share; :mod:`export.cli`
is ``python -m export``. The actor kinds and the number format are in :mod:`kiloforge`.
"""
