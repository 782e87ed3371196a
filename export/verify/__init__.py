"""Verification: the bit-exact emulator, the host build, the AVR build in simavr, the closed loop
(rungs 2-4 of the verification ladder; rung 1 is the golden files in tests/)."""
