"""The firmware contract: what the generated C, the emulator and the host harness share byte for byte
(message layout and CRC, LED colours, queue sizes, the per-tick and per-step output records)."""
