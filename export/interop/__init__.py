"""Interoperability: policies from other frameworks (ONNX in)."""
